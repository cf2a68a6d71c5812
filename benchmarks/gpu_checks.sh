#!/usr/bin/env bash
# Every GPU check and benchmark in one call, on a machine with CUDA torch and JAX (outputs under $OUT, or
# benchmarks/results/gpu). Without a package index, TorchRL's wheels come from .whl/ (see the developers' notes).
set -uo pipefail
out=${OUT:-benchmarks/results/gpu}
mkdir -p "$out"
if ! python -c "import torchrl" 2>/dev/null; then
    python -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl
    export PYTHONPATH=/tmp/site:$PWD
fi
export PYTHONPATH=${PYTHONPATH:-$PWD}
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv; python -c "import torch, jax; print('torch', torch.__version__, torch.cuda.get_device_name(0), '| jax', jax.__version__, jax.devices())"; } 2>&1 | tee "$out/device.txt"
for setting in protocol ik jaxmarl; do
    echo "== $setting" | tee -a "$out/reference_gpu.txt"
    timeout 240 python benchmarks/train.py reference --setting "$setting" --updates 3 --device cuda --threads 1 2>&1 \
        | grep -v Warning | tee -a "$out/reference_gpu.txt"
done
echo "== protocol_gnn" | tee -a "$out/reference_gpu.txt"
timeout 150 python benchmarks/train.py reference --setting protocol_gnn --updates 2 --device cuda --threads 1 2>&1 \
    | grep -v Warning | tee -a "$out/reference_gpu.txt"
