"""GIFs of evaluation episodes: one episode of a pair of teams on one grid, and the config's requests for them."""

from __future__ import annotations

from pathlib import Path

import jax
import torch
from torchrl.envs.utils import ExplorationType, set_exploration_type

from jax_env import Layout
from jax_env.render import write_gif
from torch_kitchen.env import KitchenEnv, with_transforms
from torch_kitchen.partners.pairing import make_seated_actor
from trainers.config import ConfigError
from trainers.evaluation.teams import Team


def record_gif(seat0: Team, seat1: Team, grid: Layout | str, path: Path, max_steps: int = 256, seed: int = 0) -> Path:
    """One episode of agent 0 of `seat0` with agent 1 of `seat1` on `grid`, rendered as an animated GIF."""
    kitchen = KitchenEnv(1, levels=grid, max_steps=max_steps, device=seat0.config.runtime.device, seed=seed)
    teams = [seat0] if seat0 is seat1 else [seat0, seat1]
    actor = make_seated_actor([team.actor_critic.actor for team in teams])
    seated = actor.module[0].seat(torch.tensor([[0, len(teams) - 1]], device=kitchen.device))
    env = with_transforms(kitchen, seated.env_transforms())

    def the_kitchen():
        return jax.tree_util.tree_map(lambda leaf: leaf[0], kitchen.states)

    torch.manual_seed(seed)
    tensordict = env.reset()
    frames = [the_kitchen()]
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        env.rollout(max_steps, actor, auto_reset=False, tensordict=tensordict,
                    callback=lambda env, td: frames.append(the_kitchen()))
    return Path(write_gif(frames, path))


def parse_gif_request(request: str, teams: list[Team], grids: dict[str, Layout]) -> tuple[Team, Team, Layout]:
    """"cond/seed0+cond/seed1@grid" -> (agent 0's team, agent 1's team, the test grid)."""
    pair, sep, grid = request.partition("@")
    first, plus, second = pair.partition("+")
    if not sep or not plus or not grid:
        raise ConfigError(f"gifs entry {request!r} must look like 'condition/seed0+condition/seed1@grid'")
    by_name = {team.name: team for team in teams}
    for name in (first, second):
        if name not in by_name:
            raise ConfigError(f"gifs entry {request!r} names the team {name!r}; teams: {', '.join(by_name)}")
    if grid not in grids:
        raise ConfigError(f"gifs entry {request!r} names {grid!r}, which is not a test grid: {', '.join(grids)}")
    return by_name[first], by_name[second], grids[grid]
