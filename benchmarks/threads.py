"""Training throughput by torch thread count, on a quiet machine and beside a process that keeps one core busy.

On a small shared CPU, torch's worker threads wait for each other at every operation; when another process holds
a core, a thread that was descheduled holds up all the others, and small networks can lose an order of
magnitude. Several teams trained in one process (`teams=K`) can instead learn at once, one team per thread
(`parallel_teams`), with no waiting between threads, and a team alone can compute its minibatches' shards at
once on those threads (`minibatch_shards`). This measures `trainers.ppo.loop.train_teams` (updates after the first)
for each thread count, number of teams learning at once and shards per minibatch, first alone, then beside a
busy-loop process (the OS decides where it runs), and prints the steps/s and the loaded / quiet ratio.

    python benchmarks/threads.py [--threads 1 2] [--architecture mlp] [--envs 32] [--updates 3]
    python benchmarks/threads.py --teams 2 --threads 1 --parallel-teams 1 2
    python benchmarks/threads.py --teams 1 --threads 1 --parallel-teams 2 --shards 1 2
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile

from trainers.config.compose import load_config
from trainers.machine import machine_name
from trainers.ppo.loop import train_teams
from trainers.ppo.team import team_configs

# A pure-Python busy loop: one core's worth of load, no threads of its own.
BUSY_LOOP = "while True:\n    sum(range(10000))\n"


def steps_per_second(threads: int, parallel_teams: int, shards: int, args: argparse.Namespace) -> float:
    """Mean env steps per second (all teams') of updates 2..`args.updates` with `threads` torch threads,
    `parallel_teams` teams (or one team's shards) learning at once and `shards` per minibatch."""
    rates = {}  # update -> steps/s, as every team logs it
    with tempfile.TemporaryDirectory() as run_dir:
        config = load_config(None, [
            f"architecture={args.architecture}", f"num_envs={args.envs}", f"rollout_steps={args.rollout_steps}",
            f"total_steps={args.updates * args.envs * args.rollout_steps}", f"runtime.threads={threads}",
            f"runtime.teams={args.teams}", f"runtime.parallel_teams={parallel_teams}",
            f"runtime.minibatch_shards={shards}",
            f"run_dir={run_dir}",
            "progress=false", "eval_episodes=0", "checkpoint_every=1000", "loggers=[csv]",
        ])  # fmt: skip
        train_teams(team_configs(config),
                    on_update=lambda update, metrics: rates.update({update: metrics["charts/steps_per_second"]}))
    timed = [rate for update, rate in rates.items() if update > 1]
    return sum(timed) / max(1, len(timed))


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--architecture", default="mlp")
    parser.add_argument("--envs", type=int, default=32)
    parser.add_argument("--rollout-steps", type=int, default=256)
    parser.add_argument("--updates", type=int, default=3, help="updates per measurement (the first is not timed)")
    parser.add_argument("--teams", type=int, default=1, help="teams trained in one process, each of --envs kitchens")
    parser.add_argument("--parallel-teams", nargs="+", type=int, default=[1],
                        help="teams (or one team's shards) learning at once")
    parser.add_argument("--shards", nargs="+", type=int, default=[1], help="shards per PPO minibatch")
    args = parser.parse_args(argv)
    print(f"{machine_name()}; {args.architecture}, {args.teams} team(s) x {args.envs} kitchens x "
          f"{args.rollout_steps} steps, Infinite Kitchen, hidden 256")
    settings = [(threads, parallel, shards) for threads in args.threads for parallel in args.parallel_teams
                for shards in args.shards]
    quiet = {setting: steps_per_second(*setting, args) for setting in settings}
    busy = subprocess.Popen([sys.executable, "-c", BUSY_LOOP])
    try:
        loaded = {setting: steps_per_second(*setting, args) for setting in settings}
    finally:
        busy.kill()
        busy.wait()
    print("| torch threads | teams learning at once | shards per minibatch | quiet steps/s | one core busy steps/s "
          "| busy / quiet |")
    print("|---:|---:|---:|---:|---:|---:|")
    for setting in settings:
        print(f"| {setting[0]} | {setting[1]} | {setting[2]} | {quiet[setting]:,.0f} | {loaded[setting]:,.0f} | "
              f"{loaded[setting] / quiet[setting]:.2f} |")


if __name__ == "__main__":
    main()
