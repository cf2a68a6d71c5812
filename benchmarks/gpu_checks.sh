#!/usr/bin/env bash
# Every GPU check and benchmark in one call, on a machine with CUDA torch and JAX. Without a package index,
# TorchRL's wheels come from .whl/ (`make gpu-offline`).
#
# The rows run one at a time, alone on the machine, in order of what they tell: the paper's protocol with the default
# collector first, ours against the pure-JAX yardstick in the same run; the main job (`make main DEVICE=cuda` less its
# set-up: the user's first command) last, with what is left. A row is skipped (saying so) once less than its timeout
# is left of BUDGET_S seconds (default 540: one call of a 10-minute limit, with set-up), counted from the script's
# start, less RESERVE_S (default 20) kept for the record. Every row goes into the record with its status (finished,
# failed, timed out, skipped) and the tail of its output: benchmarks/gpu_record.py writes
# $RESULTS/<date>_<device>.json and .md (RESULTS defaults to benchmarks/results/gpu; on a lent machine, the folder
# that comes back), per row the command, ours, the yardstick, the ratio and PASS/FAIL against the goals, and the raw
# outputs in a folder beside them.
#
# DEVICE=cpu SIZE=tiny: a dry run of every path in seconds (the suite runs it, so the script cannot rot between
# lendings). ONLY=<regex> runs the rows whose name matches it (e.g. ONLY=main for the main job alone).
# EXTRA_ROW="NAME TIMEOUT COMMAND..." adds a row of your own after the others, before the main job.
set -uo pipefail
device=${DEVICE:-cuda}
budget=${BUDGET_S:-540}
reserve=${RESERVE_S:-20}
results=${RESULTS:-benchmarks/results/gpu}
raw=$(mktemp -d)
records=$raw/records.jsonl
if [[ ${SIZE:-full} == tiny ]]; then
    protocol=tiny jaxmarl=tiny ik=tiny updates=2 repeats=1 envs=4 steps=8 cook_envs=4
    strangers_args="--heldout 1 --rollouts 1"
    main_args="num_envs=4 rollout_steps=16 max_steps=16 hidden=16 total_steps=64 distill.kitchens=4 distill.rounds=1
        distill.epochs=1 eval_episodes=0 runtime.threads=1 runtime.collector=kitchen"
else
    protocol=protocol jaxmarl=jaxmarl ik=ik updates=3 repeats=3 envs=192 steps=300 cook_envs=4096 main_args=""
    strangers_args="--heldout 100 --rollouts 4"
fi
# Where the machine has python3 alone, `python` (every row's command) is python3.
if ! command -v python >/dev/null; then
    mkdir -p "$raw/bin" && ln -s "$(command -v python3)" "$raw/bin/python" && export PATH=$raw/bin:$PATH
fi
if ! python -c "import torchrl" 2>/dev/null; then
    python -m pip install -q --no-index --no-deps --no-compile --target /tmp/site .whl/*.whl
    export PYTHONPATH=/tmp/site:$PWD
fi
export PYTHONPATH=${PYTHONPATH:-$PWD}
# Pure-Python packages a bare machine may lack (the config loader's OmegaConf, the reference's Flax and Optax):
# copies of the set-up's, last on the path (`make gpu-offline`).
[[ -d .whl/site ]] && export PYTHONPATH=$PYTHONPATH:$PWD/.whl/site
# The device, and a missing package stops the call here, before any device time goes on rows that cannot start
# (one interpreter for both: each start imports torch and JAX anew).
nvidia-smi --query-gpu=name,memory.total,driver_version --format=csv > "$raw/device.txt" 2>/dev/null
if ! python -W ignore -c "import torchrl, flax, optax, trainers.ppo.loop, torch_kitchen.env, torch, jax
print('torch', torch.__version__, torch.cuda.get_device_name(0) if torch.cuda.is_available() else 'no CUDA',
      '| jax', jax.__version__, jax.devices())" >> "$raw/device.txt" 2>&1; then
    cat "$raw/device.txt"; echo "gpu_checks: the imports above fail (make gpu-offline, then carry .whl)"; exit 1
fi
cat "$raw/device.txt"

# row NAME TIMEOUT COMMAND...: runs COMMAND with TIMEOUT seconds, its output into NAME.txt (shown less warnings), and
# its status into the record; its figures, where it has any, it writes itself (`--record`).
row() {
    local name=$1 limit=$2 started=$SECONDS status
    shift 2
    [[ -n ${ONLY:-} && ! $name =~ $ONLY ]] && return
    if (( limit <= 0 || budget - reserve - SECONDS < limit )); then
        echo "== $name skipped (${limit} s needed, $(( budget - reserve - SECONDS )) s left)"
        python benchmarks/gpu_record.py status "$records" "$name" skipped 0 "$*"
        return
    fi
    echo "== $name: $*"
    GPU_CHECK_ROW=$name timeout "$limit" "$@" > "$raw/$name.txt" 2>&1
    status=$?
    grep -v Warning "$raw/$name.txt"
    python benchmarks/gpu_record.py status "$records" "$name" "$status" $(( SECONDS - started )) "$*" \
        --output "$raw/$name.txt"
}

reference="python benchmarks/train.py reference --device $device --threads 1 --updates $updates --repeats $repeats --record $records"
# The headline: the paper's protocol (c) with the default collector (the teams act inside the kitchens' XLA
# program), then acting step by step from torch, with the compiled update (CUDA graphs), and with the stacked
# acting networks compiled too.
row protocol_default 200 $reference --setting $protocol
row protocol_kitchen 200 $reference --setting $protocol --collector kitchen
row protocol_update_compiled 200 $reference --setting $protocol --update-compiled true
row protocol_all_compiled 180 $reference --setting $protocol --update-compiled true --compile --collector kitchen
# What the host does per step and minibatch, where a batch's time goes, and the floor.
row launches 90 python benchmarks/launches.py --setting $protocol --teams 1 6 --device "$device"
row phases 120 python benchmarks/phases.py --setting $protocol --updates $updates --device "$device"
row collection 90 python benchmarks/collection.py --setting ik --envs $envs --steps $steps --device "$device"
# The same for the main job's team (the agent-centred MLP at hidden 128), whose default collector is the XLA one too.
row ego_rollout 90 python benchmarks/collection.py --setting ik --envs $envs --steps $steps --device "$device" \
    architecture=ego_mlp hidden=128
# How the XLA rollout takes its inputs from torch: copied (the default), without command buffers, shared.
row xla_inputs 120 python benchmarks/xla_rollout_inputs.py --envs $envs --device "$device"
# The scripted cook inside XLA on the device (its waves, and its floor tables kept) against the torch cook on the host.
row scripted_cook 90 python benchmarks/scripted_cook.py --envs $cook_envs --calls 10
# IPPO beside zoo cooks planning inside the same program, against self-play at the planner-guided shape.
row zoo_partners 150 python benchmarks/zoo_partners.py --updates $updates --rounds 1 --device "$device" --out "$raw/zoo_partners.md"
# Evaluation beside the zoo's strangers, inside XLA and by the kitchens' collector.
row strangers 200 python benchmarks/strangers.py $strangers_args --workers 1 --device "$device" --out "$raw/strangers.md"
# The other settings: one team at the paper's shape (b), JaxMARL's (a).
row ik_default 150 $reference --setting $ik
row jaxmarl_default 150 $reference --setting $jaxmarl
row jaxmarl_update_compiled 150 $reference --setting $jaxmarl --update-compiled true
[[ $protocol == protocol ]] && row protocol_gnn 150 $reference --setting protocol_gnn
# The SK configs' networks, one per agent (inside XLA too), against the yardstick's per-agent networks.
[[ $protocol == protocol ]] && row protocol_sk 150 $reference --setting protocol_sk
# The syncs torch reports in two updates (its warnings are the output: kept whole).
if [[ -z ${ONLY:-} || sync_audit =~ $ONLY ]] && (( budget - reserve - SECONDS >= 90 )) && [[ $device == cuda ]]; then
    timeout 90 python -c "
import sys, warnings, torch
warnings.simplefilter('always')
sys.path.insert(0, 'benchmarks')
sys.argv = ['train.py', 'throughput', '--archs', 'mlp', '--envs', '32', '--updates', '2', '--device', 'cuda']
torch.cuda.set_sync_debug_mode('warn')
import train
train.main()
" > "$raw/sync_audit.txt" 2>&1
    echo "torch sync warnings in 2 updates at 32 x 256: $(grep -c synchronizing "$raw/sync_audit.txt")"
fi

[[ -n ${EXTRA_ROW:-} ]] && row $EXTRA_ROW
# The main job last, alone, with what is left of the budget: its wall time is the user's.
row main $(( budget - reserve - SECONDS )) python -m trainers.train_command configs/main.yaml runtime.device="$device" \
    run_dir="$raw/main" progress=false $main_args
python benchmarks/gpu_record.py write "$records" "$raw" --out "$results"
