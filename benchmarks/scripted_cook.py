"""Milliseconds per call of the scripted cook (`torch_kitchen.scripted.ScriptedCook`) on a batch of kitchens, the
5 expanded layouts and held-out levels as evaluation seats it, beside a trained team's actor (MLP, hidden 64) on
the same observations in the same run: the scripted partner's share of an evaluation step.

    python benchmarks/scripted_cook.py [--envs 1024] [--calls 10]
"""

from __future__ import annotations

import argparse

import torch
from timing import seconds_per_call

from jax_env import EXPANDED_LAYOUTS
from torch_kitchen.env import KitchenEnv
from torch_kitchen.models import make_actor_critic
from torch_kitchen.scripted import ScriptedCook
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
    machine = machine_name()
    print(f"{machine}, torch threads 1, {args.envs} kitchens")
    print(f"scripted cook {scripted:.1f} ms, MLP actor {mlp:.1f} ms, ratio {scripted / mlp:.1f}")


if __name__ == "__main__":
    main()
