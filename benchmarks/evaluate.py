"""Evaluation throughput: episodes per second of self-play / cross-play, and the paper's protocol estimated.

A population of 6 teams (random weights: speed does not depend on them) of one architecture plays its 36 ordered
pairs on the test grids, through the evaluator's own batch routine (`KitchenEnv` pinned to the grids, a
`SeatedPolicy`, the shared collector). One batch of `--envs` kitchens is played once to compile and once timed.
The reference, in the same run: JaxMARL's Overcooked stepping the same number of kitchens with random actions in
one jitted scan, no networks (the env alone, the floor of any JaxMARL evaluation).

    python benchmarks/evaluate.py [--archs mlp gnn] [--envs 1024 4096] [--threads 2] [--device cpu]
"""

from __future__ import annotations

import argparse
import time

import torch
from env_step import jaxmarl_env, make_rollout, per_second

from jax_env import EXPANDED_LAYOUTS, get_layout
from torch_kitchen.env import KitchenEnv
from torch_kitchen.models import make_actor_critic
from torch_kitchen.partners.pairing import make_seated_actor
from trainers.config import TrainConfig
from trainers.evaluation import Team, evaluation_grids, make_matchups
from trainers.machine import THREADS_HELP, machine_name
from trainers.ppo.collection import play_episodes

SEEDS, STEPS = 6, 256
PROTOCOL_EPISODES = SEEDS * SEEDS * 105 * 100  # 36 pairs x 105 grids x 100 rollouts, per condition


def population(architecture: str, hidden: int) -> list[Team]:
    teams = []
    for seed in range(SEEDS):
        torch.manual_seed(seed)
        actor_critic = make_actor_critic(architecture, (7, 7, 26), hidden, share_params=True)
        config = TrainConfig(architecture=architecture, seed=seed, hidden=hidden)
        teams.append(Team(f"{architecture}/seed{seed}", architecture, config, actor_critic, (7, 7, 26), ""))
    return teams


def episodes_per_second(architecture: str, hidden: int, num_envs: int, device: str) -> float:
    """Episodes per second of one timed batch of `num_envs` kitchens (all 36 pairs, 105 grids, pinned)."""
    teams = population(architecture, hidden)
    teams, matchups = make_matchups({architecture: teams})
    grids = evaluation_grids(EXPANDED_LAYOUTS, 100)
    env = KitchenEnv(num_envs, levels=grids, max_steps=STEPS, device=device, pin_levels=True)
    actor = make_seated_actor([team.actor_critic.actor.to(device) for team in teams])
    seats = torch.tensor([[m.seat0, m.seat1] for m in matchups], device=device)
    actor.module[0].seat(seats[torch.arange(num_envs, device=device) % len(matchups)])
    with torch.no_grad():
        play_episodes(env, actor, STEPS)  # compiles the env's step
        start = time.perf_counter()
        play_episodes(env, actor, STEPS)
        if device.startswith("cuda"):
            torch.cuda.synchronize()
    return num_envs / (time.perf_counter() - start)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--archs", nargs="+", default=["mlp", "gnn"])
    parser.add_argument("--envs", nargs="+", type=int, default=[1024, 4096])
    parser.add_argument("--hidden", type=int, default=256)
    parser.add_argument("--threads", type=int, default=1, help=THREADS_HELP)
    parser.add_argument("--device", default="cpu")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    print(f"device: {args.device}, {machine_name()}, torch threads: {args.threads}, "
          f"hidden {args.hidden}, 6 teams (36 pairs), {STEPS}-step episodes")
    layout = get_layout("cramped_room_7x7")
    reference = jaxmarl_env(layout, STEPS)
    print(f"{'architecture':>12s} {'envs':>6s} {'episodes/s':>11s} {'JaxMARL env alone':>18s} {'ratio':>6s} "
          f"{'protocol (1 condition)':>23s}")
    for num_envs in args.envs:
        rollout = make_rollout(reference.reset, reference.step, lambda a: {"agent_0": a[:, 0], "agent_1": a[:, 1]},
                               num_envs, STEPS)
        reference_eps = per_second(rollout, num_envs, min_seconds=2.0)
        for architecture in args.archs:
            eps = episodes_per_second(architecture, args.hidden, num_envs, args.device)
            hours = PROTOCOL_EPISODES / eps / 3600
            print(f"{architecture:>12s} {num_envs:6d} {eps:11,.1f} {reference_eps:18,.1f} {eps / reference_eps:6.2f} "
                  f"{hours:20.1f} h", flush=True)
    print(f"protocol: {PROTOCOL_EPISODES:,} episodes per condition (36 pairs x 105 grids x 100 rollouts)")


if __name__ == "__main__":
    main()
