"""Env steps per second through the TorchRL `KitchenEnv` against the raw jitted JAX stepper, same run.

Raw: the jitted batched step (`vmap(step_env)` + observations, the same JAX call `KitchenEnv` makes) driven
from Python with random actions. TorchRL: `env.rollout` with random actions, and a `Collector` with a
`RandomPolicy`, each with partial resets at episode ends. In brackets: the share of the raw throughput kept.

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


def raw_steps_per_second(env: KitchenEnv, steps: int) -> float:
    """The JAX call of `KitchenEnv._step`, with random actions made on the device, no torch in the loop."""
    env.reset()
    step = env._step_jax
    states, deliveries = env._states, env._deliveries
    key = jax.device_put(jax.random.PRNGKey(0), env._jax_device)
    random_actions = jax.jit(lambda k: jax.random.randint(k, (env.num_envs, 2), 0, 6, dtype=jnp.int32))
    states, deliveries, out = step(states, deliveries, random_actions(key))  # compile
    jax.block_until_ready(out)
    start = time.perf_counter()
    for t in range(steps):
        states, deliveries, out = step(states, deliveries, random_actions(jax.random.fold_in(key, t)))
    jax.block_until_ready(out)
    return env.num_envs * steps / (time.perf_counter() - start)


def rollout_steps_per_second(env: KitchenEnv, steps: int, contiguous: bool) -> float:
    """`env.rollout`; `contiguous=False` keeps the steps as a lazy stack instead of copying them into one."""
    env.rollout(8, break_when_any_done=False)  # compile
    start = time.perf_counter()
    env.rollout(steps, break_when_any_done=False, return_contiguous=contiguous)
    return env.num_envs * steps / (time.perf_counter() - start)


def collector_steps_per_second(env: KitchenEnv, steps: int) -> float:
    frames = env.num_envs * steps
    collector = Collector(env, RandomPolicy(env.full_action_spec), frames_per_batch=frames, total_frames=5 * frames)
    iterator = iter(collector)
    next(iterator)  # compile and warm up
    start = time.perf_counter()
    collected = sum(batch.numel() for batch in iterator)
    elapsed = time.perf_counter() - start
    collector.shutdown()
    return collected / elapsed


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", nargs="+", type=int, default=[1024, 8192])
    parser.add_argument(
        "--frames", type=int, default=262_144, help="env steps per measurement (a rollout holds them all in memory)"
    )
    parser.add_argument("--levels", default="infinite")
    parser.add_argument("--device", default="cpu")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)

    print(f"device: {args.device} (jax: {jax.devices()[0].device_kind}), levels: {args.levels}")
    columns = ["raw JAX", "rollout (lazy)", "rollout (stacked)", "Collector"]
    print(f"{'envs':>6s} " + " ".join(f"{name + ' steps/s':>24s}" for name in columns))
    for num_envs in args.envs:
        env = KitchenEnv(num_envs=num_envs, levels=args.levels, max_steps=256, device=args.device)
        steps = max(8, args.frames // num_envs)
        raw = raw_steps_per_second(env, steps)
        torchrl = [
            rollout_steps_per_second(env, steps, contiguous=False),
            rollout_steps_per_second(env, steps, contiguous=True),
            collector_steps_per_second(env, steps),
        ]
        cells = [f"{raw:,.0f}"] + [f"{sps:,.0f} ({sps / raw:.0%})" for sps in torchrl]
        print(f"{num_envs:6d} " + " ".join(f"{cell:>24s}" for cell in cells), flush=True)


if __name__ == "__main__":
    main()
