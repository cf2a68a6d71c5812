"""Infinite Kitchen throughput: levels generated per second, and env steps per second with a new generated
level at every auto-reset against a fixed layout.

Stepping runs `Overcooked.step_batch` (the batched step that generates levels only when an episode ends) in a
`jax.lax.scan` with random actions and 256-step episodes; `jax.vmap(step)`, which computes a reset at every
step as JaxMARL does, is shown too.

    python benchmarks/generator.py [--envs 1024 8192]
    python benchmarks/generator.py --sizes 7 9 [--levels 20000] [--envs 1024]

`--sizes`: per kitchen size, `--levels` training levels checked by the solvability checker (how many unsolvable,
how many held-out grids drawn), the levels/s, and the env steps/s on generated kitchens of that size, against
the first size's.
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import numpy as np
from env_step import make_rollout, per_second

from jax_env import GeneratorConfig, Overcooked, heldout_grids, sample_levels, sample_training_levels
from jax_env.solvability import UNSOLVABLE, classify_levels


def level_sampler(num_levels, training, config=GeneratorConfig()):
    heldout = heldout_grids(config)
    if training:
        return lambda key: sample_training_levels(jax.random.split(key, num_levels), config, heldout)
    return lambda key: sample_levels(jax.random.split(key, num_levels), config)


def batched_rollout(env, num_envs, num_steps):
    """Like `env_step.make_rollout`, but through `Overcooked.step_batch`."""

    def rollout(key):
        obs, states = env.reset_batch(key, num_envs)

        def body(carry, key):
            obs, states = carry
            key_act, key_step = jax.random.split(key)
            actions = jax.random.randint(key_act, (num_envs, 2), 0, 6, dtype=jnp.int32)
            obs, states, *_ = env.step_batch(key_step, states, actions)
            return (obs, states), None

        return jax.lax.scan(body, (obs, states), jax.random.split(key, num_steps))[0]

    return jax.jit(rollout)


def by_size(sizes: list[int], num_levels: int, num_envs: int, num_steps: int, min_seconds: float) -> None:
    """Per kitchen size: unsolvable and held-out levels among `num_levels` training levels, levels/s, env steps/s
    on generated kitchens, and that against the first size's."""
    print(f"{'size':>5s} {'levels checked':>15s} {'unsolvable':>11s} {'held-out drawn':>15s} {'levels/s':>10s} "
          f"{'env steps/s':>12s} {'vs first':>9s}")
    first = None
    for size in sizes:
        config = GeneratorConfig(size=size)
        heldout = {grid.tobytes() for grid in np.asarray(heldout_grids(config))}
        levels = jax.tree_util.tree_map(np.asarray, level_sampler(num_levels, True, config)(jax.random.PRNGKey(1)))
        cells = np.stack([levels.agent_pos % size, levels.agent_pos // size], axis=-1)  # (x, y) of each agent
        unsolvable = int((classify_levels(levels.grid, cells) == UNSOLVABLE).sum())
        drawn = sum(grid.tobytes() in heldout for grid in levels.grid)
        rate = per_second(level_sampler(num_envs, True, config), num_envs, min_seconds)
        env = Overcooked("infinite", max_steps=256, generator=config)
        steps = per_second(batched_rollout(env, num_envs, num_steps), num_envs * num_steps, min_seconds)
        first = first or steps
        print(f"{size:>5d} {num_levels:15,d} {unsolvable:11d} {drawn:15d} {rate:10,.0f} {steps:12,.0f} "
              f"{steps / first:9.2f}", flush=True)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", type=int, default=[1024, 8192])
    parser.add_argument("--steps", type=int, default=512, help="steps per jitted rollout (2 episodes)")
    parser.add_argument("--min-seconds", type=float, default=3.0)
    parser.add_argument("--sizes", nargs="+", type=int, help="compare kitchen sizes instead (e.g. 7 9)")
    parser.add_argument("--levels", type=int, default=20_000, help="with --sizes: training levels checked")
    args = parser.parse_args(argv)
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()})")
    if args.sizes:
        by_size(args.sizes, args.levels, args.envs[0], args.steps, args.min_seconds)
        return

    print(f"{'levels per call':>16s} {'levels/s':>12s} {'training levels/s (held-out rejected)':>40s}")
    for n in args.envs:
        plain = per_second(level_sampler(n, training=False), n, args.min_seconds)
        training = per_second(level_sampler(n, training=True), n, args.min_seconds)
        print(f"{n:16d} {plain:12,.0f} {training:40,.0f}", flush=True)

    fixed = Overcooked("cramped_room_7x7", max_steps=256)
    infinite = Overcooked("infinite", max_steps=256)
    print(f"{'envs':>6s} {'fixed steps/s':>14s} {'infinite steps/s':>17s} {'cost':>6s} {'infinite, vmap(step)':>21s}")
    for n in args.envs:
        fixed_sps = per_second(batched_rollout(fixed, n, args.steps), n * args.steps, args.min_seconds)
        infinite_sps = per_second(batched_rollout(infinite, n, args.steps), n * args.steps, args.min_seconds)
        every_step = make_rollout(infinite.reset, infinite.step, lambda a: a, n, args.steps)
        every_step_sps = per_second(every_step, n * args.steps, args.min_seconds)
        cost = 1 - infinite_sps / fixed_sps
        print(f"{n:6d} {fixed_sps:14,.0f} {infinite_sps:17,.0f} {cost:6.1%} {every_step_sps:21,.0f}", flush=True)


if __name__ == "__main__":
    main()
