"""Training throughput by torch thread count, on a quiet machine and beside a process that keeps one core busy.

On a small shared CPU, torch's worker threads wait for each other at every operation; when another process holds
a core, a thread that was descheduled holds up all the others, and small networks can lose an order of
magnitude. This measures `trainers.ippo.train` (updates after the first) for each thread count, first alone,
then beside a busy-loop process (the OS decides where it runs), and prints the
steps/s and the loaded / quiet ratio.

    python benchmarks/threads.py [--threads 1 2] [--architecture mlp] [--envs 32] [--updates 3]
"""

from __future__ import annotations

import argparse
import os
import platform
import subprocess
import sys
import tempfile

from trainers.config import load_config
from trainers.ippo import train

# A pure-Python busy loop: one core's worth of load, no threads of its own.
BUSY_LOOP = "while True:\n    sum(range(10000))\n"


def steps_per_second(threads: int, architecture: str, num_envs: int, rollout_steps: int, updates: int) -> float:
    """Mean env steps per second of updates 2..`updates` with `threads` torch threads."""
    rates = []
    with tempfile.TemporaryDirectory() as run_dir:
        config = load_config(None, [
            f"architecture={architecture}", f"num_envs={num_envs}", f"rollout_steps={rollout_steps}",
            f"total_steps={updates * num_envs * rollout_steps}", f"threads={threads}", f"run_dir={run_dir}",
            "progress=false", "eval_episodes=0", "checkpoint_every=1000", "loggers=[csv]",
        ])  # fmt: skip
        train(config, on_update=lambda update, metrics: rates.append(metrics["charts/steps_per_second"]) and False)
    return sum(rates[1:]) / max(1, len(rates) - 1)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--threads", nargs="+", type=int, default=[1, 2])
    parser.add_argument("--architecture", default="mlp")
    parser.add_argument("--envs", type=int, default=32)
    parser.add_argument("--rollout-steps", type=int, default=256)
    parser.add_argument("--updates", type=int, default=3, help="updates per measurement (the first is not timed)")
    args = parser.parse_args(argv)
    print(f"{platform.processor() or platform.machine()}, {os.cpu_count()} cores; {args.architecture}, "
          f"{args.envs} kitchens x {args.rollout_steps} steps, Infinite Kitchen, hidden 256")
    quiet = {n: steps_per_second(n, args.architecture, args.envs, args.rollout_steps, args.updates)
             for n in args.threads}
    busy = subprocess.Popen([sys.executable, "-c", BUSY_LOOP])
    try:
        loaded = {n: steps_per_second(n, args.architecture, args.envs, args.rollout_steps, args.updates)
                  for n in args.threads}
    finally:
        busy.kill()
        busy.wait()
    print("| torch threads | quiet steps/s | one core busy steps/s | busy / quiet |")
    print("|---:|---:|---:|---:|")
    for n in args.threads:
        print(f"| {n} | {quiet[n]:,.0f} | {loaded[n]:,.0f} | {loaded[n] / quiet[n]:.2f} |")


if __name__ == "__main__":
    main()
