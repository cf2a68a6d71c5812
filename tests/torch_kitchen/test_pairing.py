"""Seated policies: each seat acts exactly as its team would alone; pinned levels stay with their kitchens."""

import numpy as np
import pytest
import torch
from tensordict import TensorDict
from torchrl.envs import Compose, TransformedEnv
from torchrl.envs.utils import ExplorationType, set_exploration_type

from jax_env import get_layout
from torch_kitchen.env import KitchenEnv
from torch_kitchen.models import make_actor_critic
from torch_kitchen.partners.pairing import make_seated_actor

GRIDS = ["cramped_room_7x7", "coord_ring_7x7", "forced_coord_7x7"]


def test_every_seat_acts_as_its_team_alone_and_carries_its_own_memory():
    torch.manual_seed(0)
    teams = [
        make_actor_critic("mlp", hidden=16, share_params=False),
        make_actor_critic("mlp_lstm", hidden=16, share_params=False),
        make_actor_critic("gnn_lstm", hidden=8, share_params=True),
        make_actor_critic("mlp_lstm", hidden=16, share_params=True),  # same width as team 1: one shared storage
    ]
    seats = torch.tensor([[0, 1], [1, 2], [2, 2], [3, 1], [1, 0], [2, 3], [3, 3], [0, 0]])
    actor = make_seated_actor([team.actor for team in teams])
    seated = actor.module[0].seat(seats)
    env = TransformedEnv(KitchenEnv(len(seats), levels="infinite", max_steps=5, seed=1),
                         Compose(*seated.env_transforms()))
    with set_exploration_type(ExplorationType.RANDOM), torch.no_grad():
        rollout = env.rollout(9, actor, break_when_any_done=False)  # an episode end (and memory reset) inside
    assert rollout["is_init"][:, 5].all() and not rollout["is_init"][:, 4].any()

    for k, team in enumerate(teams):
        # The team alone, replayed along the recorded observations: its logits must be the seated ones.
        state = {}
        for t in range(rollout.shape[1]):
            step = TensorDict({("agents", "observation"): rollout["agents", "observation"][:, t],
                               "is_init": rollout["is_init"][:, t], **state}, batch_size=[len(seats)])
            with torch.no_grad():
                step = team.actor(step)
            if team.recurrent:
                state = {("agents", n): step["next", "agents", n] for n in ("actor_h", "actor_c")}
            mine = seats == k
            torch.testing.assert_close(rollout["agents", "logits"][:, t][mine], step["agents", "logits"][mine])


def test_seating_is_checked():
    actor = make_seated_actor([make_actor_critic("mlp", hidden=8).actor])
    with pytest.raises(ValueError, match=r"team indices must lie in \[0, 1\)"):
        actor.module[0].seat(torch.tensor([[0, 1]]))
    with pytest.raises(ValueError, match="teams must be"):
        actor.module[0].seat(torch.tensor([0, 0]))


def test_pinned_kitchens_keep_their_levels_across_episodes():
    env = KitchenEnv(7, levels=GRIDS, max_steps=3, seed=0, pin_levels=True)
    expected = np.stack([get_layout(GRIDS[b % 3]).grid for b in range(7)])
    env.reset()
    np.testing.assert_array_equal(np.asarray(env.states.grid), expected)
    env.rollout(10, break_when_any_done=False)  # three episode ends, partial resets included
    np.testing.assert_array_equal(np.asarray(env.states.grid), expected)
    # Unpinned, the same list draws levels at random.
    free = KitchenEnv(7, levels=GRIDS, max_steps=3, seed=0)
    free.reset()
    assert not np.array_equal(np.asarray(free.states.grid), expected)
    with pytest.raises(ValueError, match="pin_levels needs a list of levels"):
        KitchenEnv(2, levels="infinite", pin_levels=True)
