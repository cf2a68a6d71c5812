"""Infinite Kitchen throughput: levels generated per second, and env steps per second with a new generated
level at every auto-reset against a fixed layout.

Stepping runs `Overcooked.step_batch` (the batched step that generates levels only when an episode ends) in a
`jax.lax.scan` with random actions and 256-step episodes; `jax.vmap(step)`, which computes a reset at every
step as JaxMARL does, is shown too.

    python benchmarks/generator.py [--envs 1024 8192]
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
from env_step import make_rollout, per_second

from jax_env import GeneratorConfig, Overcooked, heldout_grids, sample_levels, sample_training_levels


def level_sampler(num_levels, training):
    config, heldout = GeneratorConfig(), heldout_grids()
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


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", type=int, default=[1024, 8192])
    parser.add_argument("--steps", type=int, default=512, help="steps per jitted rollout (2 episodes)")
    parser.add_argument("--min-seconds", type=float, default=3.0)
    args = parser.parse_args(argv)
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()})")

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
