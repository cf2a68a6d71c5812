"""What each cook did at each step, read off its observations before and after: the events of ZSC-Eval's
evaluation partners, counted per seat. A convention (`torch_kitchen.partners.conventions`) prefers or avoids them; the
zoo keeps conventions whose counts differ.

    onion_pickup   its hands were empty and hold an onion     onion_in_pot   it put an onion in a pot
    plate_pickup   its hands were empty and hold a plate      soup_pickup    it took a soup (from a pot or a counter)
    serve          it put a soup on the serving counter       counter_place  it put an item on a counter
    idle           it chose to stay
"""

from __future__ import annotations

import torch
from torch import nn

from jax_env import STAY, Channel
from jax_env.state import DIR_VECTORS

EVENTS = ("onion_pickup", "onion_in_pot", "plate_pickup", "soup_pickup", "serve", "counter_place", "idle")


def _faced(observation: torch.Tensor) -> torch.Tensor:
    """bool [..., H, W]: the cell each observing cook faces; observation uint8 [..., H, W, 26]."""
    me = observation[..., Channel.SELF] > 0
    facing = observation[..., Channel.SELF_FACING:Channel.SELF_FACING + 4]
    faced = torch.zeros_like(me)
    height, width = me.shape[-2:]
    for direction, (dx, dy) in enumerate(DIR_VECTORS):
        looks = me & (facing[..., direction] > 0)
        padded = nn.functional.pad(looks, (1, 1, 1, 1))  # the cell at (y + dy, x + dx) of each looking cook
        faced |= padded[..., 1 - dy: 1 - dy + height, 1 - dx: 1 - dx + width]
    return faced


def kitchen_events(observation: torch.Tensor, action: torch.Tensor, next_observation: torch.Tensor) -> torch.Tensor:
    """float32 [..., E]: which of `EVENTS` each cook's step made happen (0 or 1), from its observation uint8
    [..., H, W, 26] before and after the step and its action long [...]."""

    def holds(obs, channel):
        return ((obs[..., Channel.SELF] > 0) & (obs[..., channel] > 0)).flatten(-2).any(-1)

    onion, plate, soup = (holds(observation, c) for c in (Channel.ONION, Channel.PLATE, Channel.SOUP))
    onion_after, plate_after, soup_after = (holds(next_observation, c)
                                            for c in (Channel.ONION, Channel.PLATE, Channel.SOUP))
    empty, empty_after = ~(onion | plate | soup), ~(onion_after | plate_after | soup_after)
    faced = _faced(observation)

    def facing(channel):
        return (faced & (observation[..., channel] > 0)).flatten(-2).any(-1)

    let_go = ~empty & empty_after
    events = [
        empty & onion_after,
        onion & empty_after & facing(Channel.POT),
        empty & plate_after,
        ~soup & soup_after,
        soup & empty_after & facing(Channel.GOAL),
        let_go & facing(Channel.EMPTY_COUNTER),
        action == STAY,
    ]
    return torch.stack(events, -1).float()
