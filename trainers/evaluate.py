"""Evaluating a trained team: self-play deliveries per test grid, a Markdown/CSV table, and a GIF.

The test grids are the paper's: the 5 expanded classic layouts and the generated levels held out of
training. Episodes come from the same collector routine as training (`trainers.rollout`), with actions
sampled from the policy.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass
from pathlib import Path

import jax
import numpy as np
import torch
from torchrl.envs import TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from jax_env import EXPANDED_LAYOUTS, Layout, get_layout, heldout_levels, layout_from_state
from jax_env.render import write_gif
from torch_kitchen.models import ActorCritic, make_actor_critic
from trainers.checkpoint import load_checkpoint
from trainers.config import TrainConfig, load_config
from trainers.ippo import make_env, with_model_transforms
from trainers.rollout import collect_episodes, finished_episode_deliveries


@dataclass
class Team:
    """A trained team: its training config, its networks, and the kitchen size they were built for."""

    config: TrainConfig
    actor_critic: ActorCritic
    obs_shape: tuple[int, int, int]
    checkpoint: str


def load_team(checkpoint: str | Path, device: str = "cpu") -> Team:
    """The trained team of a checkpoint file or run directory (a CheckpointError says why one is unusable)."""
    state = load_checkpoint(checkpoint, map_location=device)
    config = load_config(base=state["config"], overrides=[f"device={device}"])
    model = state["model"]
    actor_critic = make_actor_critic(
        model["architecture"], tuple(model["obs_shape"]), model["hidden"], model["share_params"]
    )
    actor_critic.actor.load_state_dict(state["actor"])
    actor_critic.critic.load_state_dict(state["critic"])
    actor_critic.actor.to(device).eval()
    actor_critic.critic.to(device).eval()
    return Team(config, actor_critic, tuple(model["obs_shape"]), state["path"])


def evaluation_grids(num_heldout: int = 100) -> list[Layout]:
    """The 5 expanded classic layouts, then the first `num_heldout` of the 100 held-out generated levels."""
    generated = heldout_levels()
    heldout = [
        layout_from_state(jax.tree_util.tree_map(lambda leaf, i=i: leaf[i], generated), name=f"heldout_{i:03d}")
        for i in range(min(num_heldout, int(generated.grid.shape[0])))
    ]
    return [get_layout(name) for name in EXPANDED_LAYOUTS] + heldout


def self_play_deliveries(
    config: TrainConfig, actor_critic: ActorCritic, grid: Layout | str, episodes: int, seed: int = 0
) -> torch.Tensor:
    """float32 [episodes]: deliveries of `episodes` self-play episodes on one grid."""
    env = with_model_transforms(make_env(config, num_envs=episodes, levels=grid, seed=seed), actor_critic)
    return finished_episode_deliveries(collect_episodes(env, actor_critic.actor, config.max_steps))


def record_gif(config: TrainConfig, actor_critic: ActorCritic, grid: Layout | str, path: Path, seed: int = 0) -> Path:
    """One self-play episode on `grid`, rendered as an animated GIF."""
    env = with_model_transforms(make_env(config, num_envs=1, levels=grid, seed=seed), actor_critic)
    kitchen = env.base_env if isinstance(env, TransformedEnv) else env

    def the_kitchen():
        return jax.tree_util.tree_map(lambda leaf: leaf[0], kitchen.states)

    tensordict = env.reset()
    frames = [the_kitchen()]
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        env.rollout(
            config.max_steps,
            actor_critic.actor,
            auto_reset=False,
            tensordict=tensordict,
            callback=lambda env, td: frames.append(the_kitchen()),
        )
    return Path(write_gif(frames, path))


def report_trained_team(run: str | Path, episodes: int | None = None, num_heldout: int | None = None) -> Path:
    """Self-play table of a run's latest checkpoint (eval.md, eval.csv) and a GIF (team.gif) in the run dir."""
    run = Path(run)
    team = load_team(run)
    config, actor_critic = team.config, team.actor_critic
    episodes = episodes or config.eval_episodes
    grids = evaluation_grids(config.eval_heldout if num_heldout is None else num_heldout)
    grids = [grid for grid in grids if grid.grid.shape == team.obs_shape[:2]]  # a model sees one kitchen size
    rows = []
    for grid in grids:
        deliveries = self_play_deliveries(config, actor_critic, grid, episodes, seed=config.seed)
        stderr = float(deliveries.std() / np.sqrt(len(deliveries))) if len(deliveries) > 1 else 0.0
        rows.append((grid.name, float(deliveries.mean()), stderr, len(deliveries)))

    lines = [
        f"Self-play deliveries per episode, {run} ({episodes} episodes per grid, actions sampled)",
        "",
        "| grid | mean deliveries | s.e. | episodes |",
        "|---|---:|---:|---:|",
    ]
    lines += [f"| {name} | {mean:.2f} | {stderr:.2f} | {n} |" for name, mean, stderr, n in rows]
    classic = [mean for name, mean, *_ in rows if not name.startswith("heldout")]
    generated = [mean for name, mean, *_ in rows if name.startswith("heldout")]
    if classic:
        lines.append(f"| **classic layouts (mean)** | {np.mean(classic):.2f} | | |")
    if generated:
        lines.append(f"| **held-out levels (mean)** | {np.mean(generated):.2f} | | |")
    table = "\n".join(lines) + "\n"
    (run / "eval.md").write_text(table)
    with open(run / "eval.csv", "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["grid", "mean_deliveries", "stderr", "episodes"])
        writer.writerows(rows)
    print(table)
    if config.gif and grids:
        gif = record_gif(config, actor_critic, grids[0], run / "team.gif")
        print(f"gif: {gif}")
    return run / "eval.md"

