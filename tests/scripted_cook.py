"""A scripted cook whose deliveries are known, for tests of evaluation and partner modelling.

`TWO_BOOTHS` encloses each agent in a one-cell booth with a pot, an onion pile, a plate pile and a goal on its
four sides, so an agent delivers on its own, at a fixed pace, whatever its partner does. `ScriptedCook` reads
its observation and cooks: three onions into the pot, a plate, the soup, the goal. Seats not in `working` stay.
Teams of it are registered as architectures, so they are saved and loaded like trained teams.
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from jax_env import INTERACT, STAY, Channel, parse_layout
from jax_env.state import DIR_VECTORS
from torch_kitchen.models import ActorCritic, model_identity, register_architecture
from torch_kitchen.models.acting import sampling_actor
from trainers.checkpoint import save_checkpoint
from trainers.config import TrainConfig

TWO_BOOTHS = parse_layout("WPWPW\nO0B1O\nWXWXW", name="two_booths")


class ScriptedCook(nn.Module):
    """uint8 [..., 2, H, W, 26] observations -> logits [..., 2, 6] that pick one action with certainty."""

    def __init__(self, working: tuple[int, ...] = (0, 1)):
        super().__init__()
        self.register_buffer("working", torch.tensor([seat in working for seat in range(2)]), persistent=False)

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        obs = observation.float()
        me = obs[..., Channel.SELF]  # [..., 2, H, W]: where each seat's agent stands

        def here(channel):
            return (obs[..., channel] * me).sum((-2, -1))

        # The four cells around the agent, in the order of the move actions (north, south, east, west).
        around = torch.stack([me.roll((dy, dx), (-2, -1)) for dx, dy in DIR_VECTORS], dim=-3)  # [..., 2, 4, H, W]

        def beside(channel):
            return (obs[..., channel].unsqueeze(-3) * around).sum((-2, -1))  # [..., 2, 4]

        facing = (obs[..., Channel.SELF_FACING:Channel.SELF_FACING + 4] * me.unsqueeze(-1)).sum((-3, -2)).argmax(-1)
        pot_onions = (beside(Channel.ONIONS_IN_POT) * beside(Channel.POT)).sum(-1)
        pot_busy = (beside(Channel.COOKING_OR_SOUP) * beside(Channel.POT)).sum(-1) > 0
        pot_ready = (beside(Channel.SOUP) * beside(Channel.POT)).sum(-1) > 0
        holding_soup, holding_plate = here(Channel.SOUP) > 0, here(Channel.PLATE) > 0
        holding_onion = here(Channel.ONION) > 0

        needs_onion = (pot_onions < 3) & ~pot_busy
        # Which of the tiles (goal, pot, onion pile, plate pile) to face next, and where it lies.
        tiles = torch.stack([beside(c) for c in (Channel.GOAL, Channel.POT, Channel.ONION_PILE, Channel.PLATE_PILE)],
                            dim=-1)  # [..., 2, 4 dirs, 4]
        wanted = torch.where(
            holding_soup, 0, torch.where(holding_onion | holding_plate, 1, torch.where(needs_onion, 2, 3))
        )
        direction = tiles.gather(-1, wanted[..., None, None].expand(*wanted.shape, 4, 1)).squeeze(-1).argmax(-1)
        waiting = holding_plate & ~pot_ready
        act = torch.where(facing == direction, torch.where(waiting, STAY, INTERACT), direction)
        action = torch.where(self.working, act, STAY)
        logits = torch.full((*action.shape, 6), -1e9, device=observation.device)
        return logits.scatter(-1, action.unsqueeze(-1), 0.0)


def scripted_team(working: tuple[int, ...]) -> ActorCritic:
    actor = sampling_actor(
        TensorDictModule(ScriptedCook(working), in_keys=[("agents", "observation")], out_keys=[("agents", "logits")])
    )
    critic = TensorDictModule(
        lambda obs: torch.zeros(*obs.shape[:-3], 1), in_keys=[("agents", "observation")],
        out_keys=[("agents", "state_value")],
    )  # fmt: skip
    return ActorCritic(actor=actor, critic=critic, recurrent=False)


SEATS = {"scripted_cooks": (0, 1), "scripted_cook_seat0": (0,), "scripted_cook_seat1": (1,), "scripted_idle": ()}
for _name, _seats in SEATS.items():
    try:
        register_architecture(_name, lambda obs_shape, hidden, share_params, seats=_seats: scripted_team(seats))
    except ValueError:  # registered by an earlier import of this module
        pass


def save_scripted_team(path, architecture: str, seed: int = 0, levels="infinite", shape=TWO_BOOTHS.grid.shape,
                       **config) -> str:
    """A checkpoint of a scripted team for kitchens of `shape`, as `kitchen-train` would write it (no weights:
    nothing to learn); `config`: more of its config's values."""
    config = TrainConfig(name=architecture, seed=seed, architecture=architecture, levels=levels, **config)
    obs_shape = (*shape, 26)
    save_checkpoint(path, {
        "config": config.to_dict(), "model": model_identity(architecture, obs_shape, 1, True),
        "actor": {}, "critic": {}, "update": 0, "env_steps": 0,
    })  # fmt: skip
    return str(path)
