"""Where two human proxies' games differ from the humans': what the cooks hold, how busy the pots are and what lies
on the counters, per layout, in the humans' games of one split and in games of two proxies fitted on the other.

A proxy that delivers far fewer soups than the humans did shows here where its games go: e.g. soups left waiting in
their pots while a cook holds an onion and plates lie on the counter. Every figure is read from the observations
(`jax_env.observation.Channel`), so the humans' recorded states and the proxies' played ones are measured alike.

    python benchmarks/human_proxy_states.py [--layouts forced_coord cramped_room] [--runs runs] [--out FILE]

Needs the dataset (`kitchen-humans fetch`) and the proxies fitted on the train split (`kitchen-humans train`,
`runs/bc_<layout>/seed0`); the humans are those of the test split, the proxies play as many games, as long as theirs.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
import torch

from jax_env.human_games import LAYOUTS, load_dataset
from jax_env.observation import Channel
from torch_kitchen.keys import OBSERVATION
from trainers.evaluation import load_team
from trainers.humans.behaviour_cloning import human_batch, play_together
from trainers.humans.command import DATA

COLUMNS = ("soups per game", "holding an onion", "holding a plate", "holding a soup", "pots cooking or ready",
           "soups waiting in pots", "onions on counters", "plates on counters")


def state_figures(observation: torch.Tensor) -> list[float]:
    """From uint8 observations [N, 2, H, W, 26] (seat 0's and seat 1's views): the share of cook-steps holding an
    onion, a plate, a soup; the share of pot-steps cooking or ready, ready; the mean onions and plates lying."""
    view = observation[:, 0].float()  # seat 0's view: its own layers first, the kitchen's the same for both
    cooks = view[..., Channel.SELF] + view[..., Channel.PARTNER]  # [N, H, W], 1 where a cook stands
    held = [float((cooks * view[..., channel]).sum((-1, -2)).mean() / 2)
            for channel in (Channel.ONION, Channel.PLATE, Channel.SOUP)]
    pots = view[..., Channel.POT] > 0
    busy = float((view[..., Channel.COOKING_OR_SOUP] > 0)[pots].float().mean())
    ready = float((view[..., Channel.SOUP] > 0)[pots].float().mean())
    lying = [float(((1 - cooks) * (1 - pots.float()) * view[..., channel]).sum((-1, -2)).mean())
             for channel in (Channel.ONION, Channel.PLATE)]
    return [*held, busy, ready, *lying]


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--layouts", nargs="+", default=list(LAYOUTS.values()))
    parser.add_argument("--data", type=Path, default=DATA)
    parser.add_argument("--runs", type=Path, default=Path("runs"), help="where runs/bc_<layout>/seed0 are")
    parser.add_argument("--out", type=Path, help="also write the table here")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    lines = [
        "The humans' games of the test split against as many games, as long as theirs, of two proxies fitted on "
        "the train split (`runs/bc_<layout>`, actions sampled). Holding: the share of cook-steps; pots: the share "
        "of pot-steps; counters: the mean number lying. Written by `python benchmarks/human_proxy_states.py`.",
        "",
        "| layout | who | " + " | ".join(COLUMNS) + " |",
        "|---|---|" + "---:|" * len(COLUMNS),
    ]
    for layout in args.layouts:
        games = load_dataset(args.data, "test", layout)
        steps = int(round(np.mean([len(game) for game in games])))
        humans = [float(np.mean([game.deliveries for game in games])),
                  *state_figures(human_batch(games).get(OBSERVATION))]
        rollout = play_together(load_team(args.runs / f"bc_{layout}" / "seed0").actor_critic, layout, steps,
                                len(games))
        soups = float(rollout.get(("next", "deliveries")).sum() / len(games))
        proxies = [soups, *state_figures(rollout.get(OBSERVATION).flatten(0, 1))]
        for who, figures in (("humans", humans), ("two proxies", proxies)):
            lines.append(f"| {layout} | {who} | " + " | ".join(f"{value:.2f}" for value in figures) + " |")
            print(lines[-1], flush=True)
    table = "\n".join(lines) + "\n"
    if args.out is not None:
        args.out.write_text(table)
    print(table)


if __name__ == "__main__":
    main()
