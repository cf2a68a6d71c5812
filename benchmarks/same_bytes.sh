#!/bin/bash
# What fixed seeds learn, compared between an earlier revision and the working tree: six short runs from each
# (IPPO MLP with the XLA collector and annealing, MLP in two shards with the kitchens' collector, three teams on
# two threads, GNN in shards, per-agent LSTM, E3T with two teams) write their CSV logs, compared file by file with
# `cmp`, the timing metrics aside. A few minutes on two cores. (A compiled update equals eager to float rounding
# only, so a change to what it traces may change its last bits: it is not among them.)
#
#     bash benchmarks/same_bytes.sh 032d6da [OUT]
set -euo pipefail
REV=$1; OUT=${2:-$(mktemp -d)}
ROOT=$(cd "$(dirname "$0")/.." && pwd); PY=${PYTHON:-$ROOT/.venv/bin/python}
EARLIER=$OUT/tree-$REV
git -C "$ROOT" worktree add -f --detach "$EARLIER" "$REV" >/dev/null
trap 'git -C "$ROOT" worktree remove --force "$EARLIER"' EXIT
common="progress=false runtime.threads=1 checkpoint_every=1000 eval_episodes=0 num_envs=16 rollout_steps=128"

runs() {  # TREE LOGS
  local tree=$1 logs=$2
  run() { local name=$1; shift
    (cd "$tree" && PYTHONPATH=$tree "$PY" -m trainers.train_command "$@" $common run_dir="$logs/$name" \
      > "$logs/$name.log" 2>&1) || echo "$name: failed in $tree (see $logs/$name.log)"; }
  mkdir -p "$logs"
  run mlp configs/ippo/mlp_sk_cramped_room.yaml total_steps=65536 ppo.shaping_weight=1 ppo.anneal_lr=true
  run mlp_kitchen configs/ippo/mlp_sk_cramped_room.yaml total_steps=32768 runtime.collector=kitchen hidden=128
  run teams3 configs/ippo/mlp_sk_cramped_room.yaml total_steps=16384 runtime.teams=3 runtime.parallel_teams=2
  run gnn_shards configs/ippo/gnn_sk_cramped_room.yaml total_steps=8192 runtime.minibatch_shards=2
  run lstm configs/ippo/mlp_lstm_sk_cramped_room.yaml total_steps=8192 share_params=false
  run e3t configs/e3t/mlp_sk_cramped_room.yaml total_steps=8192 runtime.teams=2
}
runs "$EARLIER" "$OUT/earlier"
runs "$ROOT" "$OUT/current"

same=0; differ=0
for file in $(cd "$OUT/earlier" && find . -path '*/csv/*' -name '*.csv' | sort); do
  case $file in *collect_seconds*|*update_seconds*|*steps_per_second*) continue;; esac
  if cmp -s "$OUT/earlier/$file" "$OUT/current/$file"; then same=$((same + 1)); else differ=$((differ + 1)); echo "differs: $file"; fi
done
echo "CSV files of $REV and the working tree: $same the same, $differ differ (timing metrics aside; logs in $OUT)"
