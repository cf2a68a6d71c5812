"""Training throughput (collection + PPO update) per architecture, and a learning check.

Throughput: env steps per second of `trainers.ppo.loop.train` for each architecture and batch size, timed on the
updates after the first (which compiles the env). E3T: the same for E3T and for IPPO with the same encoder, one
after the other in the same run, and their ratio. Learning check: Single Kitchen on `cramped_room_7x7` with the
MLP and the shaped reward, run until the mean deliveries of the last episodes reach the target (or the budget
ends), reporting steps and wall time. Reference: our trainer and the pure-JAX PPO of `benchmarks/jax_ppo.py` (a
yardstick: the whole run compiled as one XLA program) on the same kitchens, network and batch, in one run, and
the ratio of their steps/s.

    python benchmarks/train.py throughput [--archs mlp gnn] [--envs 32 1024] [--device cpu|cuda] [key=value ...]
    python benchmarks/train.py e3t [--encoders mlp gnn] [--envs 32] [--device cpu|cuda]
    python benchmarks/train.py learning [--target 5] [--budget 2e7] [--threads 2] [key=value ...]
    python benchmarks/train.py reference [--setting jaxmarl|ik|protocol|protocol_gnn|protocol_sk] [--updates 3]
                                         [--compile] [--update-compiled true] [--collector kitchen|torchrl|xla]
    python benchmarks/train.py parity [--setting jaxmarl] [--budget 3e6] [--rows 10] [--seed 0]
    python benchmarks/train.py profile [--setting jaxmarl|ik] [--updates 12] [--rows 40] [--collector xla]
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from collections import deque
from collections.abc import Sequence

import torch

from trainers.config.compose import load_config
from trainers.machine import THREADS_HELP, machine_name
from trainers.ppo.loop import train, train_teams
from trainers.ppo.team import team_configs


def throughput(architecture: str, num_envs: int, rollout_steps: int, updates: int, device: str, threads: int,
               algorithm: str = "ippo", overrides: Sequence[str] = ()) -> float:
    """Mean env steps per second of updates 2..`updates` (collection + PPO epochs; all teams' steps with `teams=K`);
    `overrides` (key=value) come last."""
    rates = {}  # update -> steps/s of the batch, as the last team to learn from it logs it
    with tempfile.TemporaryDirectory() as run_dir:
        config = load_config(
            None,
            [
                f"architecture={architecture}",
                f"algorithm={algorithm}",
                f"num_envs={num_envs}",
                f"rollout_steps={rollout_steps}",
                f"total_steps={updates * num_envs * rollout_steps}",
                f"runtime.device={device}",
                f"runtime.threads={threads}",
                f"run_dir={run_dir}",
                "progress=false",
                "eval_episodes=0",
                "checkpoint_every=1000",
                *overrides,
            ],
        )
        train_teams(team_configs(config),
                    on_update=lambda update, metrics: rates.update({update: metrics["charts/steps_per_second"]}))
    timed = [rate for update, rate in rates.items() if update > 1]
    return sum(timed) / max(1, len(timed))


def learning_check(target: float, budget: int, threads: int, device: str, seed: int, overrides: list[str]) -> None:
    """SK cramped_room_7x7, MLP, shaped reward annealed over the first 2.5M steps; stops at the target.

    Defaults follow JaxMARL's IPPO for Overcooked (16 kitchens x 128 steps per update): four times more gradient
    steps per env step than the paper's 32 x 256, which matters on a CPU budget. `overrides` change any of it.
    """
    start = time.perf_counter()
    reached = {}
    with tempfile.TemporaryDirectory() as run_dir:
        config = load_config(
            "configs/ippo/mlp_sk_cramped_room.yaml",
            [
                "num_envs=16",
                "rollout_steps=128",
                "ppo.shaping_weight=1.0",
                "ppo.shaping_anneal_steps=2.5e6",
                f"total_steps={budget}",
                f"runtime.threads={threads}",
                f"runtime.device={device}",
                f"seed={seed}",
                f"run_dir={run_dir}",
                "progress=false",
                "eval_episodes=0",
                "checkpoint_every=1000",
                *overrides,
            ],
        )
        episodes_per_update = config.frames_per_batch / config.max_steps
        recent = deque(maxlen=max(1, round(128 / episodes_per_update)))  # about the last 128 episodes

        def on_update(update, metrics):
            if "charts/episode_deliveries" in metrics:  # logged on updates where some episode ended
                recent.append(metrics["charts/episode_deliveries"])
            mean = sum(recent) / max(1, len(recent))
            steps = update * config.frames_per_batch
            if update % 20 == 0:
                print(f"  {steps:>11,} steps  {time.perf_counter() - start:7.0f} s  deliveries {mean:5.2f}", flush=True)
            if len(recent) == recent.maxlen and mean >= target:
                reached.update(steps=steps, seconds=time.perf_counter() - start, deliveries=mean)
                return True
            return False

        train(config, on_update=on_update)
    if reached:
        print(
            f"reached {reached['deliveries']:.2f} deliveries per episode (target {target}) after "
            f"{reached['steps']:,} steps in {reached['seconds']:.0f} s"
        )
    else:
        print(f"target {target} not reached within {budget:,} steps ({time.perf_counter() - start:.0f} s)")


def reference(setting: str, updates: int, device: str, threads: int, compile_policy: bool = False,
              compile_update: bool = False, collector: str | None = None, repeats: int = 3,
              record: str | None = None) -> None:
    """Steps/s of our trainer (updates 2..`updates`) and of the JAX reference (all `updates`, compilation excluded,
    the median of `repeats` runs) on one setting of `benchmarks/jax_ppo.py`, one after the other, and their ratio;
    `collector` None is the trainer's default. With `record`, the figures are appended to that file as a JSON line.

    The reference runs as one XLA program on JAX's own CPU thread pool, as the JAX env inside our trainer does;
    `threads` sets torch's threads only.
    """
    from jax_ppo import SETTINGS, check_supported, run_reference, setting_overrides  # with the test extra

    overrides = [*setting_overrides(setting), f"runtime.compile_policy={compile_policy}",
                 f"runtime.compile_update={compile_update}",
                 *([f"runtime.collector={collector}"] if collector else [])]
    num_envs, rollout_steps = SETTINGS[setting]["num_envs"], SETTINGS[setting]["rollout_steps"]
    ours = throughput("mlp", num_envs, rollout_steps, updates, device, threads, overrides=overrides)
    config = load_config(None, [*overrides, f"total_steps={updates * num_envs * rollout_steps}",
                                f"runtime.device={device}", f"runtime.threads={threads}"])
    print(f"setting {setting}: {' '.join(overrides)} (collector {config.runtime.collector})")
    figures = {"setting": setting, "collector": config.runtime.collector, "compile_policy": compile_policy,
               "compile_update": compile_update, "device": device, "ours": ours, "reference": None, "ratio": None}
    try:
        check_supported(config)
    except ValueError as error:  # the yardstick has only the MLP
        print(f"{'ours steps/s':>13s}\n{ours:13,.0f}   (no reference: {error})", flush=True)
    else:
        jax_rate, _ = run_reference(config, repeats=repeats)
        figures.update(reference=jax_rate, ratio=ours / jax_rate)
        print(f"{'ours steps/s':>13s} {'JAX steps/s':>12s} {'ours / JAX':>11s}")
        print(f"{ours:13,.0f} {jax_rate:12,.0f} {ours / jax_rate:11.3f}", flush=True)
    if record:
        with open(record, "a") as file:
            row = os.environ.get("GPU_CHECK_ROW", "reference")  # the row's name in benchmarks/gpu_checks.sh
            file.write(json.dumps({"row": row, "command": " ".join(["python", *sys.argv]), **figures}) + "\n")


def profile(setting: str, updates: int, threads: int, rows: int, device: str = "cpu", collector: str = "kitchen"
            ) -> None:
    """Where our trainer's time goes on one setting: collection and update seconds per batch (updates 2..N), then
    cProfile's functions by cumulative time over the whole run (the first update compiles the env)."""
    import cProfile
    import pstats

    from jax_ppo import SETTINGS, setting_overrides

    frames = SETTINGS[setting]["num_envs"] * SETTINGS[setting]["rollout_steps"]
    seconds = {}
    with tempfile.TemporaryDirectory() as run_dir:
        overrides = [f"total_steps={updates * frames}", f"runtime.threads={threads}", f"runtime.device={device}",
                     f"run_dir={run_dir}", "progress=false", "eval_episodes=0", "checkpoint_every=1000",
                     f"runtime.collector={collector}"]
        config = load_config(None, [*setting_overrides(setting), *overrides])
        profiler = cProfile.Profile()
        profiler.enable()
        train(config, on_update=lambda update, metrics: seconds.update(
            {update: (metrics["charts/collect_seconds"], metrics["charts/update_seconds"])}))
        profiler.disable()
    timed = [value for update, value in seconds.items() if update > 1]
    collect, update = (sum(column) / len(timed) for column in zip(*timed))
    print(f"setting {setting}, {config.frames_per_batch:,} steps per batch, under the profiler: collection "
          f"{collect:.3f} s ({collect / config.rollout_steps * 1e3:.2f} ms per step), update {update:.3f} s "
          f"({update / (config.ppo.epochs * config.ppo.minibatches) * 1e3:.1f} ms per minibatch)")
    pstats.Stats(profiler).sort_stats("cumulative").print_stats(rows)


def parity(setting: str, budget: int, rows: int, threads: int, seed: int) -> None:
    """Learning per sample of ours and of the JAX reference on one setting of `benchmarks/jax_ppo.py`, in one run:
    the mean deliveries per episode of the episodes that ended in each `budget / rows` window of env steps."""
    import numpy as np
    from jax_ppo import pooled_deliveries, run_reference, setting_overrides

    overrides = [*setting_overrides(setting), f"total_steps={budget}", f"runtime.threads={threads}", f"seed={seed}"]
    ours = []  # (env steps, mean deliveries of the episodes that ended in the update, or None)
    with tempfile.TemporaryDirectory() as run_dir:
        config = load_config(None, [*overrides, f"run_dir={run_dir}", "progress=false", "eval_episodes=0",
                                    "checkpoint_every=1000000", "loggers=[csv]"])

        def on_update(update, metrics):
            ours.append((update * config.frames_per_batch, metrics.get("charts/episode_deliveries")))

        started = time.perf_counter()
        train(config, on_update=on_update)
        ours_seconds = time.perf_counter() - started
    rate, reference = run_reference(config)
    steps, window = np.asarray(reference["charts/env_steps"]), budget / rows
    print(f"setting {setting}, seed {seed}: ours {ours_seconds:.0f} s ({budget / ours_seconds:,.0f} steps/s), "
          f"reference {budget / rate:.0f} s ({rate:,.0f} steps/s)")
    print(f"{'env steps up to':>16s} {'ours deliveries':>16s} {'reference deliveries':>21s}")
    for row in range(1, rows + 1):
        low, high = (row - 1) * window, row * window
        # All kitchens start together and episodes have one length: every update where some end ends all of them.
        mine = [value for step, value in ours if low < step <= high and value is not None]
        mine_mean = sum(mine) / len(mine) if mine else float("nan")
        theirs = pooled_deliveries(reference, (steps > low) & (steps <= high))
        print(f"{high:16,.0f} {mine_mean:16.2f} {theirs:21.2f}", flush=True)


def train_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="mode", required=True)
    speed = sub.add_parser("throughput")
    speed.add_argument("--archs", nargs="+", default=["mlp", "mlp_lstm", "gnn", "gnn_lstm"])
    speed.add_argument("--envs", nargs="+", type=int, default=[32, 1024])
    speed.add_argument("--updates", type=int, default=3, help="updates per measurement (the first is not timed)")
    speed.add_argument("--frames", type=int, default=65_536, help="env steps per update at large batches")
    speed.add_argument("--device", default="cpu")
    speed.add_argument("--threads", type=int, default=1, help=THREADS_HELP)
    speed.add_argument("overrides", nargs="*", help="config overrides, key=value (e.g. runtime.compile_update=true)")
    e3t = sub.add_parser("e3t")
    e3t.add_argument("--encoders", nargs="+", default=["mlp", "gnn"])
    e3t.add_argument("--envs", nargs="+", type=int, default=[32])
    e3t.add_argument("--updates", type=int, default=3, help="updates per measurement (the first is not timed)")
    e3t.add_argument("--device", default="cpu")
    e3t.add_argument("--threads", type=int, default=1, help=THREADS_HELP)
    learn = sub.add_parser("learning")
    learn.add_argument("--target", type=float, default=5.0)
    learn.add_argument("--budget", type=float, default=2e7)
    learn.add_argument("--threads", type=int, default=1, help=THREADS_HELP)
    learn.add_argument("--device", default="cpu")
    learn.add_argument("--seed", type=int, default=0)
    learn.add_argument("overrides", nargs="*", help="config overrides, key=value")
    ref = sub.add_parser("reference")
    ref.add_argument("--setting", choices=["jaxmarl", "ik", "protocol", "protocol_gnn", "protocol_sk", "tiny"],
                     default="jaxmarl")
    ref.add_argument("--updates", type=int, default=3, help="updates per measurement (ours: the first is not timed)")
    ref.add_argument("--device", default="cpu")
    ref.add_argument("--threads", type=int, default=1, help=THREADS_HELP)
    ref.add_argument("--compile", action="store_true", help="ours with compile_policy=true")
    ref.add_argument("--update-compiled", choices=["false", "true"], default="false",
                     help="ours with compile_update (the minibatch step compiled; CUDA graphs on a GPU)")
    ref.add_argument("--collector", choices=["kitchen", "torchrl", "xla"],
                     help="ours with this runtime.collector (default: the trainer's; xla: the MLP teams act inside "
                          "the kitchens' program)")
    ref.add_argument("--repeats", type=int, default=3, help="timed runs of the reference (the median is kept)")
    ref.add_argument("--record", help="append the figures to this file as a JSON line")
    prof = sub.add_parser("profile")
    prof.add_argument("--setting", choices=["jaxmarl", "ik"], default="jaxmarl")
    prof.add_argument("--updates", type=int, default=12)
    prof.add_argument("--threads", type=int, default=1)
    prof.add_argument("--rows", type=int, default=40, help="functions listed")
    prof.add_argument("--device", default="cpu")
    prof.add_argument("--collector", choices=["kitchen", "torchrl", "xla"], default="kitchen")
    par = sub.add_parser("parity")
    par.add_argument("--setting", choices=["jaxmarl", "ik"], default="jaxmarl")
    par.add_argument("--budget", type=float, default=3e6)
    par.add_argument("--rows", type=int, default=10)
    par.add_argument("--seed", type=int, default=0)
    par.add_argument("--device", default="cpu")
    par.add_argument("--threads", type=int, default=1)
    return parser


def e3t_table(args: argparse.Namespace) -> None:
    """E3T's steps per second against IPPO's, per encoder and number of kitchens."""
    print(f"{'encoder':>8s} {'envs':>6s} {'IPPO steps/s':>13s} {'E3T steps/s':>12s} {'E3T / IPPO':>11s}")
    for encoder in args.encoders:
        for num_envs in args.envs:
            ippo = throughput(encoder, num_envs, 256, args.updates, args.device, args.threads)
            e3t = throughput(f"e3t_{encoder}", num_envs, 256, args.updates, args.device, args.threads, "e3t")
            print(f"{encoder:>8s} {num_envs:6d} {ippo:13,.0f} {e3t:12,.0f} {e3t / ippo:11.2f}", flush=True)


def throughput_table(args: argparse.Namespace) -> None:
    """Steps per second per architecture and number of kitchens."""
    print(f"{'architecture':>12s} {'envs':>6s} {'rollout':>8s} {'steps/s':>10s}")
    for architecture in args.archs:
        for num_envs in args.envs:
            # The paper's 256-step rollouts at 32 envs; shorter ones keep large batches within memory and time.
            rollout_steps = 256 if num_envs * 256 <= args.frames else max(16, args.frames // num_envs)
            sps = throughput(architecture, num_envs, rollout_steps, args.updates, args.device, args.threads,
                             overrides=args.overrides)
            print(f"{architecture:>12s} {num_envs:6d} {rollout_steps:8d} {sps:10,.0f}", flush=True)


def main(argv=None):
    parser = train_parser()
    args = parser.parse_args(argv)
    print(f"device: {args.device}, {machine_name()}, torch threads: {args.threads}")

    if args.mode == "parity":
        parity(args.setting, int(args.budget), args.rows, args.threads, args.seed)
        return

    if args.mode == "profile":
        profile(args.setting, args.updates, args.threads, args.rows, args.device, args.collector)
        return
    if args.mode == "reference":
        reference(args.setting, args.updates, args.device, args.threads, args.compile, args.update_compiled == "true",
                  args.collector, args.repeats, args.record)
        return
    if args.mode == "learning":
        learning_check(args.target, int(args.budget), args.threads, args.device, args.seed, args.overrides)
        return
    if args.mode == "e3t":
        e3t_table(args)
        return
    throughput_table(args)


if __name__ == "__main__":
    torch.set_num_threads(1)
    main()
