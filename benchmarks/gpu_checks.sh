#!/usr/bin/env bash
# Every GPU check and benchmark in one call, on a machine with CUDA torch and JAX (outputs under $OUT, or
# benchmarks/results/gpu). Without a package index, TorchRL's wheels come from .whl/ (see the developers' notes).
# Order: what costs least and tells most first, so a short loan still brings back the counts and the floor.
set -uo pipefail
out=${OUT:-benchmarks/results/gpu}
mkdir -p "$out"
if ! python -c "import torchrl" 2>/dev/null; then
    python -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl
    export PYTHONPATH=/tmp/site:$PWD
fi
export PYTHONPATH=${PYTHONPATH:-$PWD}
{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv; python -c "import torch, jax; print('torch', torch.__version__, torch.cuda.get_device_name(0), '| jax', jax.__version__, jax.devices())"; } 2>&1 | tee "$out/device.txt"
# Launches and host syncs per env step, GAE and minibatch (1 and 6 teams), and the JAX step alone at the
# protocol's 192 kitchens: the floor under any trainer over this env.
timeout 120 python benchmarks/launches.py --setting protocol --teams 1 6 --device cuda 2>&1 | grep -v Warning | tee "$out/launches_gpu.txt"
timeout 90 python benchmarks/collection.py --setting ik --envs 192 --steps 300 --device cuda 2>&1 | grep -v Warning | tee "$out/collection_gpu.txt"
# Where a batch's time goes: collection, GAE and update, wall time against GPU busy time; then the host syncs the
# device reports itself.
timeout 150 python benchmarks/phases.py --setting protocol --updates 3 --device cuda 2>&1 | grep -v Warning | tee "$out/phases_gpu.txt"
timeout 90 python -c "
import torch, sys, warnings; warnings.simplefilter('always'); sys.argv = ['train.py', 'throughput', '--archs', 'mlp', '--envs', '32', '--updates', '2', '--device', 'cuda']
sys.path.insert(0, 'benchmarks'); torch.cuda.set_sync_debug_mode('warn'); import train; train.main()
" 2>&1 | grep -c "synchronizing" | sed 's/^/sync warnings in 2 updates at 32 x 256: /' | tee "$out/sync_audit_gpu.txt"
# Ours against the pure-JAX yardstick in the same run, eager and with the compiled update (CUDA graphs).
for setting in protocol ik jaxmarl; do
    for compiled in false true; do
        echo "== $setting compile_update=$compiled" | tee -a "$out/reference_gpu.txt"
        timeout 200 python benchmarks/train.py reference --setting "$setting" --updates 3 --device cuda --threads 1 \
            --update-compiled "$compiled" 2>&1 | grep -v Warning | tee -a "$out/reference_gpu.txt"
    done
done
# Everything on: the stacked acting networks replayed as CUDA graphs too (compile_policy).
echo "== protocol compile_update=true compile_policy=true" | tee -a "$out/reference_gpu.txt"
timeout 200 python benchmarks/train.py reference --setting protocol --updates 3 --device cuda --threads 1 \
    --update-compiled true --compile 2>&1 | grep -v Warning | tee -a "$out/reference_gpu.txt"
echo "== protocol_gnn" | tee -a "$out/reference_gpu.txt"
timeout 150 python benchmarks/train.py reference --setting protocol_gnn --updates 2 --device cuda --threads 1 2>&1 \
    | grep -v Warning | tee -a "$out/reference_gpu.txt"
