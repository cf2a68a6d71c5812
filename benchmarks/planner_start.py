"""IPPO from scratch against the planner-guided learner on the Infinite Kitchen, same config and seeds: deliveries
on held-out levels (self-play, cross-play between seeds, with the scripted cook) against env steps and CPU minutes.

The planner-guided learner first distils the scripted cook (`kitchen-distill`: DAgger, the config's rounds) and
then trains IPPO from it (`init_from`); the other trains IPPO from scratch, whatever the config starts from. Both
train `--config` (default: the main job's) for `--budget`
IPPO steps into `--runs/<learner>/`, one run after the other, keeping a snapshot of the team every `--every`
updates with the env steps and the CPU minutes spent so far (this process's, distillation's included; the
distilled team itself is the first snapshot). Then every snapshot taken by all seeds plays `--rollouts` episodes
on each of the first `--heldout` held-out levels; the table goes to stdout and `--out`, the curves against CPU
minutes to `--figure`.

    python benchmarks/planner_start.py --budget 1572864 --every 48 --seeds 0 1 --heldout 20 --rollouts 2 \
        --out benchmarks/results/planner_start_cpu.md --figure docs/planner_start_cpu.png
"""

from __future__ import annotations

import argparse
import csv
import shutil
import time
from collections import defaultdict
from pathlib import Path

import numpy as np

from trainers.config import DeviceConfig, EvalConfig
from trainers.config.compose import load_config
from trainers.evaluation import evaluate
from trainers.machine import machine_name
from trainers.ppo.distill import distill
from trainers.ppo.loop import train

ROOT = Path(__file__).resolve().parents[1]
LEARNERS = ("scratch", "planner")


def snapshot(run: Path, env_steps: int, minutes: float, into: dict) -> None:
    """Keeps the run's latest checkpoint as snapshots/step<env_steps>.pt, and when it was taken."""
    kept = run / "snapshots" / f"step{env_steps}.pt"
    kept.parent.mkdir(exist_ok=True)
    shutil.copy(run / "checkpoints" / "latest.pt", kept)
    into[env_steps] = (kept, minutes)


def train_learner(learner: str, seed: int, args) -> dict[int, tuple[Path, float]]:
    """Trains one learner's team of `seed`; returns its snapshots: env steps -> (checkpoint, CPU minutes)."""
    overrides = [*args.overrides, f"seed={seed}", f"total_steps={args.budget}", f"checkpoint_every={args.every}",
                 f"run_dir={args.runs / learner}", "eval_episodes=0", "progress=false", "init_from="]
    snapshots, started = {}, time.process_time()
    if learner == "planner":
        distilled = distill(load_config(args.config, [*overrides, "name=distilled"]))
        snapshot(distilled, 0, (time.process_time() - started) / 60, snapshots)
        overrides.append(f"init_from={distilled}")
    config = load_config(args.config, overrides)
    frames = config.frames_per_batch
    minutes_at = {}

    def on_update(update: int, metrics: dict) -> None:
        minutes_at[update] = (time.process_time() - started) / 60
        if update > 1 and (update - 1) % args.every == 0:  # the checkpoint of update - 1 is the latest
            snapshot(config.run_path, (update - 1) * frames, minutes_at[update - 1], snapshots)

    train(config, on_update=on_update)
    snapshot(config.run_path, config.num_updates * frames, minutes_at[config.num_updates], snapshots)
    return snapshots


def evaluate_snapshots(snapshots: dict[str, list[dict]], args) -> list[dict]:
    """One row per learner and snapshot step that every seed reached: SP, XP and with-cook deliveries."""
    conditions, minutes = {}, {}
    for learner, by_seed in snapshots.items():
        for steps in sorted(set.intersection(*[set(seed) for seed in by_seed])):
            name = f"{learner}@{steps}"
            conditions[name] = [str(seed[steps][0]) for seed in by_seed]
            minutes[name] = float(np.mean([seed[steps][1] for seed in by_seed]))
    out = args.runs / "eval"
    max_steps = load_config(args.config, args.overrides).max_steps  # episodes as long as the training ones
    evaluate(EvalConfig(conditions=conditions, layouts=[], heldout=args.heldout, rollouts=args.rollouts,
                        max_steps=max_steps, progress=False, out_dir=str(out),
                        runtime=DeviceConfig(threads=args.threads)).check())
    kinds = defaultdict(list)
    with open(out / "pairs.csv") as handle:
        for row in csv.DictReader(handle):
            condition = row["condition0"] if row["condition0"] in conditions else row["condition1"]
            kinds[condition, row["kind"]].append(float(row["mean_deliveries"]))
    rows = []
    for name in conditions:
        learner, steps = name.split("@")
        rows.append({"learner": learner, "env steps": int(steps), "CPU minutes": minutes[name],
                     **{kind: float(np.mean(kinds[name, kind])) if kinds[name, kind] else float("nan")
                        for kind in ("SP", "XP", "partner")}})
    return rows


def table(rows: list[dict], args) -> str:
    config = " ".join([f"`{args.config.relative_to(ROOT)}`", *args.overrides])
    lines = [f"Machine: {machine_name()}; {config}, seeds "
             f"{' '.join(map(str, args.seeds))}; {args.heldout} held-out levels x {args.rollouts} episodes.", "",
             "| learner | env steps | CPU minutes | SP | XP | with the scripted cook |",
             "|---|---:|---:|---:|---:|---:|"]
    for row in rows:
        lines.append(f"| {row['learner']} | {row['env steps']:,} | {row['CPU minutes']:.2f} | {row['SP']:.2f} | "
                     f"{row['XP']:.2f} | {row['partner']:.2f} |")
    return "\n".join(lines) + "\n"


def draw_curves(rows: list[dict], path: Path) -> Path:
    """SP, XP and play with the scripted cook on the held-out levels against CPU minutes, one line per learner."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    kinds = {"SP": "self-play", "XP": "cross-play between seeds", "partner": "with the scripted cook"}
    figure, axes = plt.subplots(1, len(kinds), figsize=(12, 3.4), sharey=True)
    for axis, (kind, title) in zip(axes, kinds.items()):
        for learner in LEARNERS:
            points = sorted((row["CPU minutes"], row[kind]) for row in rows if row["learner"] == learner)
            axis.plot(*zip(*points), marker="o", label=learner)
        axis.set(title=title, xlabel="CPU minutes")
        axis.grid(alpha=0.3)
    axes[0].set_ylabel("deliveries per episode, held-out levels")
    axes[0].legend()
    figure.tight_layout()
    figure.savefig(path, dpi=110)
    plt.close(figure)
    return path


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / "main.yaml")
    parser.add_argument("--budget", type=int, default=4_194_304, help="IPPO env steps per run")
    parser.add_argument("--every", type=int, default=128, help="updates between snapshots")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1])
    parser.add_argument("--heldout", type=int, default=100)
    parser.add_argument("--rollouts", type=int, default=4)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--runs", type=Path, default=ROOT / "runs" / "planner_start")
    parser.add_argument("--out", type=Path, help="also write the table here")
    parser.add_argument("--figure", type=Path, help="draw the curves against CPU minutes here (PNG)")
    parser.add_argument("overrides", nargs="*", help="key=value config overrides for both learners")
    args = parser.parse_args(argv)
    args.config = args.config.resolve()
    snapshots = {learner: [train_learner(learner, seed, args) for seed in args.seeds] for learner in LEARNERS}
    rows = evaluate_snapshots(snapshots, args)
    text = table(rows, args)
    print(text)
    if args.out:
        args.out.write_text(text)
    if args.figure:
        print(f"wrote {draw_curves(rows, args.figure)}")


if __name__ == "__main__":
    main()
