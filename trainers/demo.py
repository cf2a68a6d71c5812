"""`kitchen-demo`: play one random-policy episode in a kitchen and save it as a GIF.

    kitchen-demo --layout cramped_room_7x7 --steps 100 --out outputs/demo.gif
    python -m trainers.demo --layout path/to/kitchen.txt

`--layout` takes a registered name (see `jax_env.layouts.layout_names()`) or a text-grid file.
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import NamedTuple, Sequence

import jax
import jax.numpy as jnp

from jax_env.env import DELIVERY_REWARD, NUM_ACTIONS, Overcooked
from jax_env.layouts import load_layout
from jax_env.render import MIN_TILE_SIZE, state_to_text, write_gif
from jax_env.state import State


class Episode(NamedTuple):
    """One episode, start state included: leaves of `states` are (T + 1, ...), the rest (T, 2) float32."""

    states: State
    rewards: jax.Array
    shaped_rewards: jax.Array


def play_random_episode(env: Overcooked, key: jax.Array, steps: int) -> Episode:
    """Uniformly random actions for `steps` steps with no auto-reset, in one jitted scan."""

    def episode(key):
        key_start, key_actions = jax.random.split(key)
        start = env.initial_state(key_start)

        def one_step(state, step_key):
            actions = jax.random.randint(step_key, (2,), 0, NUM_ACTIONS, dtype=jnp.int32)
            next_state, reward, _, info = env.step_env(state, actions)
            return next_state, (next_state, reward, info["shaped_reward"])

        _, (states, rewards, shaped) = jax.lax.scan(one_step, start, jax.random.split(key_actions, steps))
        with_start = jax.tree_util.tree_map(lambda first, rest: jnp.concatenate([first[None], rest]), start, states)
        return Episode(with_start, rewards, shaped)

    return jax.jit(episode)(key)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="kitchen-demo", description=__doc__.split("\n")[0])
    parser.add_argument("--layout", default="cramped_room_7x7", help="registered layout name or text-grid file")
    parser.add_argument("--steps", type=int, default=100, help="episode length")
    parser.add_argument("--seed", type=int, default=0, help="seed of the start facings and the random actions")
    parser.add_argument("--out", default=None, help="GIF path (default outputs/demo_<layout>.gif)")
    parser.add_argument("--tile-size", type=int, default=32, help="pixels per grid cell")
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.steps < 1:
            raise ValueError(f"--steps must be positive, got {args.steps}")
        layout = load_layout(args.layout)
        env = Overcooked(layout, max_steps=args.steps)
        if args.tile_size < MIN_TILE_SIZE:
            raise ValueError(f"--tile-size must be at least {MIN_TILE_SIZE}, got {args.tile_size}")
    except (ValueError, OSError) as error:
        print(f"kitchen-demo: error: {error}", file=sys.stderr)
        return 2

    episode = play_random_episode(env, jax.random.PRNGKey(args.seed), args.steps)
    out = args.out or os.path.join("outputs", f"demo_{layout.name}.gif")
    write_gif(episode.states, out, tile_size=args.tile_size)

    final = jax.tree_util.tree_map(lambda leaf: leaf[-1], episode.states)
    deliveries = int(round(float(episode.rewards[:, 0].sum()) / DELIVERY_REWARD))
    print(state_to_text(final))
    print(f"deliveries: {deliveries}")
    shaped_per_agent = episode.shaped_rewards.sum(axis=0)
    print(
        f"shaped return: {float(shaped_per_agent.sum()):.1f} "
        f"(agent 0: {float(shaped_per_agent[0]):.1f}, agent 1: {float(shaped_per_agent[1]):.1f})"
    )
    print(f"gif: {out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
