"""Milliseconds per call of the scripted cook as torch seats it (`torch_kitchen.partners.scripted_cook.ScriptedCook`:
`jax_env.cook` with the host's floor tables by plan) on a batch of kitchens, the 5 expanded layouts and held-out levels
as evaluation seats it, beside a trained team's actor (MLP, hidden 64) on the same observations in the same run: the
scripted partner's share of an evaluation step; and the cook as a program inside XLA would call it (`cook_logits`,
jitted, on JAX's default device): running its waves each call, and reading floor tables kept through the episode (their
computation timed apart), as ratios to the seated cook's time.

    python benchmarks/scripted_cook.py [--envs 1024] [--calls 10]
"""

from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import torch
from timing import seconds_per_call

from jax_env import EXPANDED_LAYOUTS
from jax_env.cook import cook_logits, floor_tables, walkable_floor
from torch_kitchen.env import KitchenEnv
from torch_kitchen.models import make_actor_critic
from torch_kitchen.partners.scripted_cook import ScriptedCook, cook_convention
from trainers.evaluation import evaluation_grids
from trainers.machine import machine_name


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--envs", type=int, default=1024)
    parser.add_argument("--calls", type=int, default=10)
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    kitchen = KitchenEnv(args.envs, levels=evaluation_grids(list(EXPANDED_LAYOUTS), 20), pin_levels=True, seed=1)
    tensordict = kitchen.reset()
    observation = tensordict["agents", "observation"]
    cook, team = ScriptedCook(), make_actor_critic("mlp", kitchen.obs_shape, 64, True)
    with torch.no_grad():
        scripted = seconds_per_call(lambda: cook(observation), args.calls) * 1e3
        mlp = seconds_per_call(lambda: team.actor(tensordict.clone()), args.calls) * 1e3
    in_xla, tabulate = jax.jit(cook_logits), jax.jit(floor_tables)
    views, convention = jnp.asarray(observation.flatten(0, 1).numpy()), cook_convention()
    xla = seconds_per_call(lambda: in_xla(views, convention).block_until_ready(), args.calls) * 1e3
    tables = tabulate(walkable_floor(views))
    with_tables = seconds_per_call(lambda: in_xla(views, convention, tables).block_until_ready(), args.calls) * 1e3
    tabulating = seconds_per_call(lambda: tabulate(walkable_floor(views)).block_until_ready(), args.calls) * 1e3
    machine = machine_name()
    print(f"{machine}, torch threads 1, {args.envs} kitchens, JAX on {jax.devices()[0].platform}")
    print(f"scripted cook (seated from torch) {scripted:.1f} ms, MLP actor {mlp:.1f} ms, ratio {scripted / mlp:.1f}")
    print(f"scripted cook in XLA, its waves {xla:.1f} ms, {xla / scripted:.2f}x the seated cook's time")
    print(f"scripted cook in XLA, its floor tables kept {with_tables:.1f} ms, {with_tables / scripted:.2f}x the "
          f"seated cook's time; the tables, once an episode, {tabulating:.1f} ms")


if __name__ == "__main__":
    main()
