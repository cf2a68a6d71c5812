"""Env steps per second through the TorchRL `KitchenEnv` against the raw jitted JAX stepper, same run.

Two comparisons, each between like and like:

* Stepping, nothing kept. Raw: the jitted batched step that `KitchenEnv` calls, driven from Python with
  random actions made by JAX. TorchRL: `env.step_and_maybe_reset` with random actions from the action spec,
  which adds the DLPack crossing, the TensorDict and the partial resets: the cost of the layer itself.
* Trajectories, every step kept. Raw: one jitted `lax.scan` over the same step that stacks observations,
  rewards and dones into a [T, B, ...] trajectory (what a pure-JAX trainer does). TorchRL: `env.rollout`
  into a preallocated tensordict, and a `Collector` with a `RandomPolicy` configured as the trainer uses it
  (`return_same_td=True`, `compact_obs=True`, so each observation is stored once).

In brackets: the share of the raw throughput kept.

    python benchmarks/torchrl_env.py [--envs 1024 8192] [--device cpu|cuda] [--levels infinite]
"""

from __future__ import annotations

import argparse
import time

import jax
import jax.numpy as jnp
import torch
from torchrl.collectors import Collector
from torchrl.envs.utils import RandomPolicy

from torch_kitchen.env import KitchenEnv
from trainers.machine import machine_name


def _random_actions(env: KitchenEnv, key: jax.Array) -> jax.Array:
    return jax.random.randint(key, (env.num_envs, 2), 0, 6, dtype=jnp.int32)


def _synchronize(env: KitchenEnv) -> None:
    if env.device.type == "cuda":
        torch.cuda.synchronize(env.device)


def raw_step_per_second(env: KitchenEnv, steps: int) -> float:
    """The jitted step of `KitchenEnv._step` in a Python loop, nothing kept, no torch involved."""
    env.reset()
    states, deliveries = env._states, env._deliveries
    key = jax.device_put(jax.random.PRNGKey(0), env._jax_device)
    actions = jax.jit(lambda key, t: _random_actions(env, jax.random.fold_in(key, t)))
    states, deliveries, out = env._programs.step(states, deliveries, actions(key, 0))  # compile
    jax.block_until_ready(out)
    start = time.perf_counter()
    for t in range(steps):
        states, deliveries, out = env._programs.step(states, deliveries, actions(key, t))
    jax.block_until_ready(out)
    return env.num_envs * steps / (time.perf_counter() - start)


def torchrl_step_per_second(env: KitchenEnv, steps: int) -> float:
    """`env.step_and_maybe_reset` in a Python loop with random actions, nothing kept."""
    tensordict = env.reset()
    for t in range(steps + 1):
        if t == 1:  # the first step compiles
            _synchronize(env)
            start = time.perf_counter()
        tensordict = env.rand_action(tensordict)
        _, tensordict = env.step_and_maybe_reset(tensordict)
    _synchronize(env)
    return env.num_envs * steps / (time.perf_counter() - start)


def raw_trajectory_per_second(env: KitchenEnv, steps: int) -> float:
    """One jitted `lax.scan` of the same step with JAX-made random actions, returning the stacked outputs."""

    @jax.jit
    def trajectory(states, deliveries, key):
        def body(carry, key):
            states, deliveries, out = env._programs.step(*carry, _random_actions(env, key))
            return (states, deliveries), out

        return jax.lax.scan(body, (states, deliveries), jax.random.split(key, steps))

    env.reset()
    key = jax.device_put(jax.random.PRNGKey(0), env._jax_device)
    (states, deliveries), out = trajectory(env._states, env._deliveries, key)  # compile
    jax.block_until_ready(out)
    del out  # frees the memory the timed call needs
    start = time.perf_counter()
    (states, deliveries), out = trajectory(states, deliveries, key)
    jax.block_until_ready(out)
    return env.num_envs * steps / (time.perf_counter() - start)


def rollout_per_second(env: KitchenEnv, steps: int) -> float:
    """`env.rollout` writing into a preallocated tensordict (the second of two calls is timed)."""
    out = env.rollout(steps, break_when_any_done=False, return_contiguous=True)
    _synchronize(env)
    start = time.perf_counter()
    env.rollout(steps, break_when_any_done=False, out=out)
    _synchronize(env)
    return env.num_envs * steps / (time.perf_counter() - start)


def collector_per_second(env: KitchenEnv, steps: int) -> float:
    """A `Collector` with a `RandomPolicy`, batches of `steps` steps of every env, the third and fourth timed."""
    frames = env.num_envs * steps
    collector = Collector(
        env,
        RandomPolicy(env.full_action_spec),
        frames_per_batch=frames,
        total_frames=4 * frames,
        return_same_td=True,
        compact_obs=True,
    )
    iterator = iter(collector)
    next(iterator), next(iterator)  # compile, then fill the buffers once
    _synchronize(env)
    start = time.perf_counter()
    collected = sum(batch.numel() for batch in iterator)
    _synchronize(env)
    elapsed = time.perf_counter() - start
    collector.shutdown()
    return collected / elapsed


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", type=int, default=[1024, 8192])
    parser.add_argument(
        "--frames", type=int, default=262_144, help="env steps per measurement (trajectories hold them all)"
    )
    parser.add_argument("--levels", default="infinite")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    print(f"device: {args.device} (jax: {jax.devices()[0].device_kind}, {machine_name()})")
    print(f"levels: {args.levels}; steps/s, and in brackets the share of the raw figure to its left")
    header = ["raw step", "env.step", "raw trajectory", "rollout", "Collector"]
    print(f"{'envs':>6s} " + " ".join(f"{name:>18s}" for name in header))
    for num_envs in args.envs:
        env = KitchenEnv(num_envs=num_envs, levels=args.levels, max_steps=256, device=args.device)
        steps = max(8, args.frames // num_envs)
        raw_step = raw_step_per_second(env, steps)
        layer = torchrl_step_per_second(env, steps)
        raw_trajectory = raw_trajectory_per_second(env, steps)
        rollout = rollout_per_second(env, steps)
        collector = collector_per_second(env, steps)
        cells = [
            f"{raw_step:,.0f}",
            f"{layer:,.0f} ({layer / raw_step:.0%})",
            f"{raw_trajectory:,.0f}",
            f"{rollout:,.0f} ({rollout / raw_trajectory:.0%})",
            f"{collector:,.0f} ({collector / raw_trajectory:.0%})",
        ]
        print(f"{num_envs:6d} " + " ".join(f"{cell:>18s}" for cell in cells), flush=True)


if __name__ == "__main__":
    main()
