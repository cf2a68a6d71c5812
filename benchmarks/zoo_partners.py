"""IPPO with zoo partners against plain self-play at the same shape: seconds per batch of each phase and steps per
second, in one run, each variant after the other for `--rounds` rounds (the medians reported).

    self-play       algorithm=ippo, the team acting inside the kitchens' XLA program (the default collector)
    zoo, xla        algorithm=zoo_ippo: zoo cooks in a share of the kitchens, planning inside the same program
    zoo, kitchen    the same, collected by the kitchens' collector (runtime.collector=kitchen): the cooks plan
                    through `ScriptedCook` on the host, step by step
    best response   algorithm_config.best_response_to=<the zoo's first stranger>: a stranger in every kitchen

The shape defaults to the planner-guided conditions' (the agent-centred MLP, hidden 128, 32 kitchens x 256 steps):
the strangers protocol's zoo-partner condition and best responses. The goal: zoo partners at least 0.8x the steps
per second of self-play. Phases as `benchmarks/phases.py` measures them; the first update compiles and is left out.

    python benchmarks/zoo_partners.py [--updates 4] [--rounds 2] [--share 0.25] [--device cuda] [--out FILE] [k=v ...]
"""

from __future__ import annotations

import argparse
import statistics
from pathlib import Path

import torch
from phases import PHASES, phase_seconds

from torch_kitchen.partners.conventions import ZOO_FILE, load_zoo
from trainers.config.compose import load_config
from trainers.machine import machine_name

SHAPE = ["architecture=ego_mlp", "hidden=128", "share_params=true", "ppo.shaping_weight=0", "num_envs=32",
         "rollout_steps=256"]
GOAL = 0.8


def variants(share: float) -> dict[str, list[str]]:
    stranger = load_zoo(ZOO_FILE, 7).strangers[0].name
    zoo = ["algorithm=zoo_ippo", f"algorithm_config.zoo_share={share}"]
    return {
        "self-play": [],
        "zoo, xla": zoo,
        "zoo, kitchen": [*zoo, "runtime.collector=kitchen"],
        "best response": ["algorithm=zoo_ippo", f"algorithm_config.best_response_to={stranger}"],
    }


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--updates", type=int, default=4)
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--share", type=float, default=0.25)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default="benchmarks/results/zoo_partners.md", help="the table, as printed")
    parser.add_argument("overrides", nargs="*", help="config overrides, key=value")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    frames = load_config(None, ["levels=infinite", *SHAPE, *args.overrides]).frames_per_batch
    seconds: dict[str, dict[str, list[float]]] = {}
    for _ in range(args.rounds):
        for name, overrides in variants(args.share).items():
            totals = phase_seconds("ik", args.updates, args.device, [*SHAPE, *overrides, *args.overrides])
            for phase in PHASES:
                seconds.setdefault(name, {}).setdefault(phase, []).append(totals[phase][0] / (args.updates - 1))
    lines = [f"{machine_name()}, {args.device}; {frames} steps per batch ({' '.join([*SHAPE, *args.overrides])}), "
             f"zoo share {args.share}; seconds per batch, medians of {args.rounds} rounds of updates 2..{args.updates}",
             "", "| variant | collection s | advantages s | update s | steps/s | x self-play |",
             "|---|---:|---:|---:|---:|---:|"]
    rates = {}
    for name, phases in seconds.items():
        median = {phase: statistics.median(values) for phase, values in phases.items()}
        rates[name] = frames / sum(median.values())
        lines.append(f"| {name} | {median['collection']:.3f} | {median['advantages']:.3f} | {median['update']:.3f} | "
                     f"{rates[name]:.0f} | {rates[name] / rates['self-play']:.2f} |")
    ratio = rates["zoo, xla"] / rates["self-play"]
    verdict = "PASS" if ratio >= GOAL else "FAIL"
    lines += ["", f"zoo partners inside XLA: {ratio:.2f}x self-play (goal {GOAL}x): {verdict}"]
    print("\n".join(lines))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
