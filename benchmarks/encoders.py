"""Which encoder learns the Infinite Kitchen in fewer steps: architectures trained on the same config and seeds,
their training deliveries and shaped return tabulated by windows of env steps.

Each architecture trains `configs/ippo/mlp_ik.yaml` with the reduced protocol's shape (hidden 64, 16 kitchens x
128 steps, lr 1e-3, the shaped reward annealed over the run) into `--runs/<architecture>/`, one after the other;
a run already there is resumed, or read as it is if it is complete. Then the table (the mean over seeds of each
window's mean) goes to stdout and `--out`.

    python benchmarks/encoders.py --archs mlp ego_mlp --budget 1228800 --seeds 0 \
        --out benchmarks/results/encoders_ik_cpu.md

`--read RUN ...` trains nothing: it tabulates finished runs of any config, one row pair per run directory.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from trainers.config.compose import load_config
from trainers.evaluation.figures import read_scalar
from trainers.machine import machine_name
from trainers.train_command import train_or_resume

ROOT = Path(__file__).resolve().parents[1]
CONFIG = ROOT / "configs" / "ippo" / "mlp_ik.yaml"


def overrides(architecture: str, budget: int, seed: int, runs: Path) -> list[str]:
    """The one config every architecture trains with (only `architecture` and `seed` differ)."""
    return [f"architecture={architecture}", "hidden=64", "num_envs=16", "rollout_steps=128",
            f"total_steps={budget}", "ppo.lr=0.001", "ppo.shaping_weight=1.0", f"ppo.shaping_anneal_steps={budget}",
            "eval_episodes=0", "progress=false", "checkpoint_every=50", f"seed={seed}",
            f"run_dir={runs / architecture}"]


def window_means(run: Path, name: str, windows: int, budget: int) -> list[float]:
    """The mean of a logged scalar in each of `windows` equal windows of env steps (NaN where none was logged)."""
    steps, values = read_scalar(run, f"charts/{name}")
    edges = np.linspace(0, budget, windows + 1)
    return [float(values[(steps > lo) & (steps <= hi)].mean()) if ((steps > lo) & (steps <= hi)).any()
            else float("nan") for lo, hi in zip(edges[:-1], edges[1:])]


def window_rows(label: str, runs: list[Path], windows: int, budget: int) -> list[str]:
    """Markdown rows of the deliveries and shaped return of `runs`, the mean over runs of each window's mean."""
    rows = []
    for name, measure in (("episode_deliveries", "deliveries"), ("shaped_return", "shaped return")):
        means = np.nanmean([window_means(run, name, windows, budget) for run in runs], axis=0)
        rows.append(f"| {label} | {measure} | " + " | ".join(f"{value:.2f}" for value in means) + " |")
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--archs", nargs="+", default=["mlp", "ego_mlp"])
    parser.add_argument("--budget", type=int, default=1_228_800, help="env steps per run")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0])
    parser.add_argument("--windows", type=int, default=6)
    parser.add_argument("--runs", type=Path, default=ROOT / "runs" / "encoders")
    parser.add_argument("--read", type=Path, nargs="+", metavar="RUN", help="tabulate these finished runs instead")
    parser.add_argument("--out", type=Path)
    args = parser.parse_args(argv)

    if args.read:
        runs_of = {str(run): [run] for run in args.read}
        command = f"--read {' '.join(map(str, args.read))} --budget {args.budget} --windows {args.windows}"
        intro = (f"Training deliveries and shaped return per episode of each run: the mean per window of env steps, "
                 f"{args.windows} windows over {args.budget:,} steps.")
    else:
        runs_of = {}
        for architecture in args.archs:
            configs = [load_config(str(CONFIG), overrides(architecture, args.budget, seed, args.runs))
                       for seed in args.seeds]
            runs_of[architecture] = [run for config in configs for run in train_or_resume([config])]
        command = (f"--archs {' '.join(args.archs)} --budget {args.budget} --seeds {' '.join(map(str, args.seeds))} "
                   f"--runs {args.runs}")
        intro = (f"Training on the Infinite Kitchen ({CONFIG.relative_to(ROOT)}, hidden 64, 16 x 128, lr 1e-3, shaped "
                 f"reward annealed over {args.budget:,} steps), seeds {', '.join(map(str, args.seeds))}: the mean per "
                 f"window of env steps of the training episodes' deliveries and shaped return. {machine_name()}.")

    edges = np.linspace(0, args.budget, args.windows + 1) / 1e3
    columns = [f"{lo:,.0f}-{hi:,.0f}k" for lo, hi in zip(edges[:-1], edges[1:])]
    label = "run" if args.read else "architecture"
    lines = [intro, f"Command: `python benchmarks/encoders.py {command}`", "",
             f"| {label} | measure | " + " | ".join(columns) + " |", "|---|---|" + "---:|" * args.windows]
    for label, runs in runs_of.items():
        lines += window_rows(label, runs, args.windows, args.budget)
    table = "\n".join(lines) + "\n"
    print(table)
    if args.out:
        args.out.write_text(table)


if __name__ == "__main__":
    main()
