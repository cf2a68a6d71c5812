"""One team beside the held-out strangers of a zoo: the wall time of `kitchen-eval`'s stranger pass, and its
episodes per second against the scripted cook's partner pass in the same run (the reference: one cook instead of
eight conventions).

The team beside each stranger in both seats and each stranger with itself (24 pairs with 8 strangers) play `--heldout`
held-out levels x `--rollouts` episodes through `trainers.evaluation.strangers.play_with_strangers`, in `--workers`
processes; then the team beside the scripted cook in both seats and the cook with itself (3 pairs) on the same
grids through `play`. Both passes once per collector of `--collectors`, in the same run: "kitchen" (torch acts at
every step, the cooks planned from the host) and "xla" (the team's network and the cooks inside the kitchens' XLA
program, `SeatedCollector`); the strangers' own self-play beside each (the same play from other random streams). The
goal: one team against 8 strangers on 100 held-out levels x 4 rollouts in under 5 minutes on 2 cores, with the
evaluation's default collector. Writes its table to `--out` (markdown) as well as printing it.

    python benchmarks/strangers.py [--team RUN_DIR] [--heldout 100] [--rollouts 4] [--workers 2]
                                   [--collectors kitchen xla] [--device cpu]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import torch

from torch_kitchen.models import make_actor_critic
from torch_kitchen.partners.conventions import ZOO_FILE, load_zoo
from trainers.config import EVAL_COLLECTORS, EvalConfig, TrainConfig
from trainers.evaluation import Matchup, Team, evaluation_grids, load_team, play, scripted_cook_team
from trainers.evaluation.pairs import PARTNER, SP
from trainers.evaluation.strangers import play_with_strangers
from trainers.evaluation.teams import convention_team
from trainers.machine import machine_name

GOAL_S = 300.0


def untrained_team(architecture: str = "ego_mlp", hidden: int = 128) -> Team:
    """The main job's architecture with its initial weights: the speed of play does not depend on them."""
    torch.manual_seed(0)
    actor_critic = make_actor_critic(architecture, (7, 7, 26), hidden, share_params=True)
    config = TrainConfig(architecture=architecture, hidden=hidden)
    return Team(f"{architecture}/untrained", architecture, config, actor_critic, (7, 7, 26), "")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--team", help="a run directory (default: the main job's architecture, untrained)")
    parser.add_argument("--zoo", default=ZOO_FILE)
    parser.add_argument("--heldout", type=int, default=100)
    parser.add_argument("--rollouts", type=int, default=4)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--collectors", nargs="+", default=list(EVAL_COLLECTORS), choices=EVAL_COLLECTORS)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--out", default="benchmarks/results/strangers.md")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    team = load_team(args.team, args.device) if args.team else untrained_team()
    team.actor_critic.actor.to(args.device)
    strangers = [convention_team(c, (7, 7, 26), args.device) for c in load_zoo(args.zoo, 7).strangers]
    grids = evaluation_grids([], args.heldout)
    cook = scripted_cook_team((7, 7, 26), args.device)
    pairs = [Matchup(0, 1, PARTNER), Matchup(1, 0, PARTNER), Matchup(1, 1, SP)]
    stranger_episodes = (2 * len(strangers) + len(strangers)) * len(grids) * args.rollouts
    cook_episodes = len(pairs) * len(grids) * args.rollouts

    lines = [
        f"{machine_name()}, {args.device}, {args.workers} worker processes, torch threads 1; team: {team.name}; "
        f"{len(strangers)} strangers of {args.zoo}; {args.heldout} held-out levels x {args.rollouts} rollouts",
        "",
        "| collector | pass | pairs | episodes | wall s | episodes/s | strangers alone |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    seconds = {}
    for collector in args.collectors:
        start = time.perf_counter()
        met = play_with_strangers([team], strangers, grids, args.rollouts, 256, 8192, 0, args.device,
                                  workers=args.workers, collector=collector)
        seconds[collector] = time.perf_counter() - start
        start = time.perf_counter()
        play([team, cook], pairs, grids, args.rollouts, 256, 8192, 0, args.device, workers=args.workers,
             collector=collector)
        cook_s = time.perf_counter() - start
        lines += [
            f"| {collector} | beside the strangers (and each alone) | {3 * len(strangers)} | {stranger_episodes:,} | "
            f"{seconds[collector]:.1f} | {stranger_episodes / seconds[collector]:.1f} | {met.alone.mean():.2f} |",
            f"| {collector} | beside the scripted cook (and it alone): reference | {len(pairs)} | {cook_episodes:,} | "
            f"{cook_s:.1f} | {cook_episodes / cook_s:.1f} | |",
        ]
    default = EvalConfig().collector
    lines.append("")
    if len(seconds) == len(EVAL_COLLECTORS):
        ratio = seconds["kitchen"] / seconds["xla"]
        lines.append(f"The stranger pass inside XLA: {ratio:.2f}x the episodes per second of the kitchens' collector.")
    if default in seconds:
        lines.append(f"Goal: the stranger pass under {GOAL_S:.0f} s with the default collector ({default}): "
                     f"{'PASS' if seconds[default] < GOAL_S else 'FAIL'} ({seconds[default]:.0f} s).")
    table = "\n".join(lines) + "\n"
    print(table)
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(table)


if __name__ == "__main__":
    main()
