"""Distillation's rounds as they are against as they were, in one run: seconds per round (the fitting apart from the
rest: rollout, labels, value targets, checkpoint), the last round's agreement with the teacher, and the distilled
team's self-play on held-out levels; with `--seeds N`, each distilled from seeds 0 .. N-1, and each fitting's agreement
and held-out score against before's decided by a 95% stratified bootstrap interval over the seeds.

    before   the rollout by the kitchens' collector (the cook planning step by step on the host), minibatches of 4
             kitchens' whole sequences (`trainers.ppo.distill.minibatches` held to `sequences=True`), 8 passes over
             every round's data: distillation as it was (`--before` overrides)
    now      the config's own: the round inside the kitchens' XLA program, minibatches of steps drawn from every
             kitchen (and with `--also "distill.replay=1"`, say, each pass over the newest round's kitchens and as
             many drawn from the earlier rounds')

Both distil the same config (default: the main job's, `configs/main.yaml`) from the same seed, one after the other,
in this process, after one untimed round per collector that compiles what they share; then `kitchen-eval` plays each
team with itself on the first `--heldout` held-out levels. The goal: the rounds at least 3x faster than before, with
the same agreement and held-out score.

    python benchmarks/distill_rounds.py [--seeds 1] [--heldout 20] [--rollouts 4] [--also "k=v k=v"]... [--out FILE]
        [k=v ...]
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import datetime
import shutil
import time
from pathlib import Path
from unittest import mock

import numpy as np
import torch

import trainers.ppo.distill as distillation
from trainers.config import DeviceConfig, EvalConfig
from trainers.config.compose import load_config
from trainers.evaluation import evaluate
from trainers.evaluation.intervals import difference, verdict
from trainers.machine import machine_name

ROOT = Path(__file__).resolve().parents[1]
GOAL = 3.0


def timed_distillation(config, run: Path, sequences: bool) -> dict:
    """Distils `config` into `run`; returns the seconds of each round and of its fitting, and the last metrics."""
    shutil.rmtree(run, ignore_errors=True)
    fitting, rounds, metrics = [], [], {}
    plain_fit, plain_minibatches = distillation.fit, distillation.minibatches

    def timed_fit(*args, **kwargs):
        started = time.perf_counter()
        result = plain_fit(*args, **kwargs)
        fitting.append(time.perf_counter() - started)
        return result

    def on_round(round_: int, round_metrics: dict) -> None:
        rounds.append(time.perf_counter())
        metrics.update(round_metrics)

    def as_sequences(data, size, device, _sequences):
        return plain_minibatches(data, size, device, True)

    started = time.perf_counter()
    with mock.patch.object(distillation, "fit", timed_fit), \
            mock.patch.object(distillation, "minibatches", as_sequences if sequences else plain_minibatches):
        distillation.distill(config, run=run, on_round=on_round)
    ends = [started, *rounds]
    return {"round": [end - start for start, end in zip(ends, ends[1:])], "fitting": fitting,
            "agreement": metrics["distill/agreement"], "total": rounds[-1] - started}


def held_out_self_play(runs: dict[str, Path], heldout: int, rollouts: int, max_steps: int, out: Path) -> dict:
    """Each run's team with itself on the first `heldout` held-out levels: mean deliveries per episode."""
    named = {run.name: name for name, run in runs.items()}
    evaluate(EvalConfig(conditions={run.name: [str(run)] for run in runs.values()}, layouts=[], heldout=heldout,
                        rollouts=rollouts, max_steps=max_steps, partner=False, progress=False, out_dir=str(out),
                        runtime=DeviceConfig(threads=2)).check())
    with open(out / "seeds.csv") as handle:
        return {named[row["condition"]]: float(row["deliveries"]) for row in csv.DictReader(handle)
                if row["kind"] == "sp" and row["condition"] in named}


def table(results: dict, scores: dict, configs: dict, args) -> str:
    """The rounds' timings (the first seed's rounds, the mean over seeds in all), agreements and held-out scores
    (means over seeds) of every fitting; with several seeds, each against before's with its interval."""
    config = configs["now"]
    seeds = len(results["now"])
    lines = [f"Machine: {machine_name()}, torch {torch.get_num_threads()} threads, {datetime.date.today()}; "
             f"{' '.join([f'`{args.config.relative_to(ROOT)}`', *args.overrides])} ({config.distill.rounds} rounds "
             f"of {config.distill.kitchens} kitchens x {config.rollout_steps} steps, "
             f"{f'seeds 0-{seeds - 1}' if seeds > 1 else f'seed {config.seed}'}); self-play on "
             f"{args.heldout} held-out levels x {args.rollouts} episodes.", "",
             "| fitting | rollout | passes | of | minibatch | seconds per round | of which fitting | in all | "
             "x before | last agreement | held-out SP |", "|---|---|---:|---|---|---|---|---:|---:|---:|---:|"]
    total = {name: np.mean([result["total"] for result in runs]) for name, runs in results.items()}
    for name, runs in results.items():
        settings, first = configs[name].distill, runs[0]
        minibatch = f"{settings.minibatch} kitchens' sequences" if name == "before" else \
            f"{settings.minibatch * config.rollout_steps} steps"
        of = "every round" if settings.replay == 0 or settings.replay >= settings.rounds - 1 else \
            f"the newest round and {settings.replay:g}x as many earlier kitchens"
        lines.append(f"| {name} | {configs[name].runtime.collector} | {settings.epochs} | {of} | {minibatch} | "
                     f"{' '.join(f'{s:.1f}' for s in first['round'])} | "
                     f"{' '.join(f'{s:.1f}' for s in first['fitting'])} | {total[name]:.1f} | "
                     f"{total['before'] / total[name]:.2f} | "
                     f"{np.mean([result['agreement'] for result in runs]):.3f} | {np.mean(scores[name]):.2f} |")
    lines += ["", f"x before: the rounds' time in all, before's over each (goal: {GOAL:g}x with the same agreement and "
                  "held-out score as before's)."]
    if seeds > 1:
        lines += ["", f"Against before over {seeds} seeds: the difference of the means with its 95% stratified "
                      "bootstrap interval over the seeds; \"holds\" where the fitting is above before's, \"does not "
                      "hold\" where below (the goal's \"same\" fails there), else \"inconclusive\".", "",
                  "| fitting | agreement - before's | held-out SP - before's |", "|---|---|---|"]
        agreement = {name: np.array([[result["agreement"]] for result in runs]) for name, runs in results.items()}
        held_out = {name: np.array(values)[:, None] for name, values in scores.items()}
        for name in results:
            if name != "before":
                cells = [difference(measure[name], measure["before"]) for measure in (agreement, held_out)]
                lines.append(f"| {name} | " + " | ".join(f"{cell.value:+.3f} [{cell.low:+.3f}, {cell.high:+.3f}] "
                                                         f"{verdict(cell)}" for cell in cells) + " |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--config", type=Path, default=ROOT / "configs" / "main.yaml")
    parser.add_argument("--before",
                        default="distill.epochs=8 distill.minibatch=4 distill.lr=3e-3 distill.replay=0 "
                                "runtime.collector=kitchen",
                        help="overrides of the fitting as it was, in one string")
    parser.add_argument("--also", action="append", default=[], metavar="OVERRIDES",
                        help="another fitting to time beside the config's, its overrides in one string (repeatable)")
    parser.add_argument("--seeds", type=int, default=1, help="distil each fitting from seeds 0 .. N-1")
    parser.add_argument("--heldout", type=int, default=20)
    parser.add_argument("--rollouts", type=int, default=4)
    parser.add_argument("--runs", type=Path, default=ROOT / "runs" / "distill_rounds")
    parser.add_argument("--out", type=Path, help="also write the table here")
    parser.add_argument("overrides", nargs="*", help="key=value config overrides for all")
    args = parser.parse_args(argv)
    args.config = args.config.resolve()
    variants = {"before": args.before.split(), "now": [], **{also: also.split() for also in args.also}}
    configs = {name: load_config(args.config, ["progress=false", *args.overrides, *overrides])
               for name, overrides in variants.items()}
    seeds = range(args.seeds) if args.seeds > 1 else [configs["now"].seed]
    runs = {(name, seed): args.runs / f"variant{number}_seed{seed}" for number, name in enumerate(variants)
            for seed in seeds}
    # One round first per collector, untimed: the kitchens' and the cook's programs compiled for every variant alike.
    for collector in sorted({config.runtime.collector for config in configs.values()}):
        timed_distillation(load_config(args.config, ["progress=false", *args.overrides, "distill.rounds=1",
                                                     f"runtime.collector={collector}"]),
                           args.runs / f"warm_up_{collector}", sequences=False)
    results = {name: [] for name in variants}
    for seed in seeds:  # seed by seed, so that a long run gives every fitting's first seed early
        for name in variants:
            results[name].append(timed_distillation(dataclasses.replace(configs[name], seed=seed), runs[name, seed],
                                                    sequences=name == "before"))
    played = held_out_self_play(runs, args.heldout, args.rollouts, configs["now"].max_steps, args.runs / "eval")
    scores = {name: [played[name, seed] for seed in seeds] for name in variants}
    text = table(results, scores, configs, args)
    print(text)
    if args.out:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
