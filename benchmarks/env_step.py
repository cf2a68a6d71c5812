"""Env steps per second of the jitted, vmapped stepper with auto-reset, against JaxMARL's Overcooked.

Both run the same loop: `jax.lax.scan` over steps of a `jax.vmap`-ed `step` with uniformly random actions,
observations carried so none of the work can be skipped. Prints a table with the ratio and the bytes of state
per environment.

    python benchmarks/env_step.py [--layouts cramped_room counter_circuit_7x7] [--envs 1 64 1024 8192]
"""

from __future__ import annotations

import argparse
import time
import warnings

import jax
import jax.numpy as jnp
import numpy as np

from jax_env import COUNTER, FLOOR, GOAL, ONION_PILE, PLATE_PILE, POT, Overcooked, get_layout, state_nbytes
from trainers.machine import machine_name


def jaxmarl_env(layout, max_steps):
    """JaxMARL's Overcooked on the same layout (its layout dict is built from ours)."""
    from flax.core.frozen_dict import FrozenDict
    from jaxmarl.environments.overcooked.overcooked import Overcooked as ReferenceOvercooked

    flat = layout.grid.reshape(-1)
    cells = {
        "height": layout.height,
        "width": layout.width,
        "wall_idx": jnp.asarray(np.flatnonzero(flat != FLOOR)),
        "agent_idx": jnp.asarray([y * layout.width + x for x, y in layout.agent_start]),
        "goal_idx": jnp.asarray(np.flatnonzero(flat == GOAL)),
        "plate_pile_idx": jnp.asarray(np.flatnonzero(flat == PLATE_PILE)),
        "onion_pile_idx": jnp.asarray(np.flatnonzero(flat == ONION_PILE)),
        "pot_idx": jnp.asarray(np.flatnonzero(flat == POT)),
    }
    assert np.any(flat == COUNTER)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        return ReferenceOvercooked(layout=FrozenDict(cells), max_steps=max_steps)


def make_rollout(reset, step, to_actions, num_envs, num_steps):
    """A jitted function running `num_steps` auto-resetting steps of `num_envs` envs from a key."""

    def rollout(key):
        obs, state = jax.vmap(reset)(jax.random.split(key, num_envs))

        def body(carry, key):
            obs, state = carry
            key_act, key_step = jax.random.split(key)
            actions = jax.random.randint(key_act, (num_envs, 2), 0, 6, dtype=jnp.int32)
            obs, state, *_ = jax.vmap(step)(jax.random.split(key_step, num_envs), state, to_actions(actions))
            return (obs, state), None

        (obs, state), _ = jax.lax.scan(body, (obs, state), jax.random.split(key, num_steps))
        return obs, state

    return jax.jit(rollout)


def per_second(fn, items_per_call, min_seconds):
    """Items per second of a jitted `fn(key)`, timed over at least `min_seconds` after one compiling call."""
    jax.block_until_ready(fn(jax.random.PRNGKey(0)))
    calls, start = 0, time.perf_counter()
    while time.perf_counter() - start < min_seconds or calls == 0:
        jax.block_until_ready(fn(jax.random.PRNGKey(calls + 1)))
        calls += 1
    return calls * items_per_call / (time.perf_counter() - start)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--layouts", nargs="+", default=["cramped_room", "counter_circuit_7x7"])
    parser.add_argument("--envs", nargs="+", type=int, default=[1, 64, 1024, 8192])
    parser.add_argument("--steps", type=int, default=128, help="steps per jitted rollout")
    parser.add_argument("--max-steps", type=int, default=256, help="episode length (auto-resets included)")
    parser.add_argument("--min-seconds", type=float, default=2.0, help="timing window per measurement")
    args = parser.parse_args(argv)

    machine = machine_name()
    print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}), {machine}")
    print(f"{'layout':22s} {'envs':>6s} {'ours steps/s':>14s} {'JaxMARL steps/s':>16s} {'ratio':>7s}")
    for name in args.layouts:
        layout = get_layout(name)
        ours = Overcooked(layout, max_steps=args.max_steps)
        ref = jaxmarl_env(layout, args.max_steps)
        for num_envs in args.envs:
            ours_rollout = make_rollout(ours.reset, ours.step, lambda a: a, num_envs, args.steps)
            ref_rollout = make_rollout(
                ref.reset, ref.step, lambda a: {"agent_0": a[:, 0], "agent_1": a[:, 1]}, num_envs, args.steps
            )
            ours_sps = per_second(ours_rollout, num_envs * args.steps, args.min_seconds)
            ref_sps = per_second(ref_rollout, num_envs * args.steps, args.min_seconds)
            print(f"{name:22s} {num_envs:6d} {ours_sps:14,.0f} {ref_sps:16,.0f} {ours_sps / ref_sps:6.2f}x", flush=True)
        _, our_state = ours.reset(jax.random.PRNGKey(0))
        _, ref_state = ref.reset(jax.random.PRNGKey(0))
        ref_bytes = sum(np.asarray(leaf).nbytes for leaf in jax.tree_util.tree_leaves(ref_state))
        print(f"{name:22s} state bytes per env: ours {state_nbytes(our_state)}, JaxMARL {ref_bytes}")


if __name__ == "__main__":
    main()
