#!/usr/bin/env bash
# Every GPU check and benchmark in one call, on a machine with CUDA torch and JAX (outputs under $OUT, or
# benchmarks/results/gpu). Without a package index, TorchRL's wheels come from .whl/ (`make gpu-offline`).
# The steps run in order of what they tell, each within its own timeout, and a step is skipped (saying so) once
# less than its timeout is left of BUDGET_S seconds (default 540: one call of a 10-minute limit, with set-up).
# ONLY=<regex> runs the steps whose output file matches it (e.g. ONLY=main for the main job alone).
set -uo pipefail
out=${OUT:-benchmarks/results/gpu}
budget=${BUDGET_S:-540}
mkdir -p "$out"
if ! python -c "import torchrl" 2>/dev/null; then
    python -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl
    export PYTHONPATH=/tmp/site:$PWD
fi
export PYTHONPATH=${PYTHONPATH:-$PWD}
# Pure-Python packages a bare machine may lack (the config loader's OmegaConf, the reference's Flax and Optax):
# copies of the set-up's, last on the path (`make gpu-offline`).
[[ -d .whl/site ]] && export PYTHONPATH=$PYTHONPATH:$PWD/.whl/site
# A missing package stops the call here, before any device time goes on steps that cannot start.
if ! python -W ignore -c "import torchrl, flax, optax, trainers.ppo, torch_kitchen.env"; then
    echo "gpu_checks: the imports above fail (make gpu-offline, then carry .whl)"; exit 1
fi

# step FILE TIMEOUT COMMAND...: runs COMMAND with TIMEOUT seconds, appending its output (warnings dropped) to FILE.
step() {
    local file=$1 limit=$2
    shift 2
    [[ -n ${ONLY:-} && ! $file =~ $ONLY ]] && return
    if (( budget - SECONDS < limit )); then
        echo "== skipped (${limit} s needed, $(( budget - SECONDS )) s left): $*" | tee -a "$out/$file"
        return
    fi
    echo "== $*" | tee -a "$out/$file"
    timeout "$limit" "$@" 2>&1 | grep -v Warning | tee -a "$out/$file"
}

{ nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv; python -c "import torch, jax; print('torch', torch.__version__, torch.cuda.get_device_name(0), '| jax', jax.__version__, jax.devices())"; } 2>&1 | tee "$out/device.txt"
reference="python benchmarks/train.py reference --device cuda --threads 1"
# The headline first: the paper's protocol (c), ours against the pure-JAX yardstick in the same run: the teams
# acting inside the kitchens' XLA program (the default collector), then acting step by step from torch, then with
# the compiled update (CUDA graphs), and with the stacked acting networks as CUDA graphs too.
step reference_gpu.txt 200 $reference --setting protocol --updates 3
step reference_gpu.txt 200 $reference --setting protocol --updates 3 --collector kitchen
step reference_gpu.txt 200 $reference --setting protocol --updates 3 --update-compiled true
step reference_gpu.txt 180 $reference --setting protocol --updates 3 --update-compiled true --compile \
    --collector kitchen
# What the host does per step and minibatch, where a batch's time goes, the floor, and the syncs torch reports.
step launches_gpu.txt 90 python benchmarks/launches.py --setting protocol --teams 1 6 --device cuda
step phases_gpu.txt 120 python benchmarks/phases.py --setting protocol --updates 3 --device cuda
step collection_gpu.txt 90 python benchmarks/collection.py --setting ik --envs 192 --steps 300 --device cuda
# The main job end to end on the GPU (`make main DEVICE=cuda` less its set-up), and its wall time.
step main_gpu.txt 200 bash -c 'started=$SECONDS; python -m trainers.train_command configs/main.yaml \
    runtime.device=cuda run_dir=/tmp/main_gpu progress=false && echo "main job: $((SECONDS - started)) s"'
if (( budget - SECONDS >= 90 )); then  # its warnings are the output: kept whole
    timeout 90 python -c "
import sys, warnings, torch
warnings.simplefilter('always')
sys.path.insert(0, 'benchmarks')
sys.argv = ['train.py', 'throughput', '--archs', 'mlp', '--envs', '32', '--updates', '2', '--device', 'cuda']
torch.cuda.set_sync_debug_mode('warn')
import train
train.main()
" > "$out/sync_audit_gpu.txt" 2>&1
    grep -c "synchronizing" "$out/sync_audit_gpu.txt" | sed 's/^/torch sync warnings in 2 updates at 32 x 256: /'
fi
# The other settings: one team at the paper's shape (b), JaxMARL's (a), and the GNN protocol (d).
step reference_gpu.txt 150 $reference --setting ik --updates 3
step reference_gpu.txt 150 $reference --setting ik --updates 3 --update-compiled true
step reference_gpu.txt 150 $reference --setting jaxmarl --updates 3
step reference_gpu.txt 150 $reference --setting jaxmarl --updates 3 --update-compiled true
step reference_gpu.txt 150 $reference --setting protocol_gnn --updates 2
