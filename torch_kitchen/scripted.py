"""A scripted cook: a partner no team trained with, reading the same observation a trained agent reads.

It plans on the kitchen it sees, on any layout: it picks the first goal it can reach from a short list (what it
holds and what the pots need decide the list), walks the shortest path to a cell beside the goal's tile (a
breadth-first distance field), faces the tile and interacts. Where the partner stands in its way it takes a way
around the partner or waits, at random, and where both could step into one cell it steps or waits at random:
this breaks the symmetry of two cooks meeting in a corridor.

    holding a soup    the serving counter; else a counter the partner can reach (a hand-over)
    holding an onion  a pot that takes onions; else a hand-over
    holding a plate   a ready pot; else wait beside a cooking pot; else a hand-over
    empty hands       a soup on a counter; a plate if a pot cooks and the partner holds no plate; an onion if a
                      pot takes onions; then a plate, then an onion (from a pile or a counter)

Where nothing on its list is reachable it picks an action at random. Two of it deliver on every expanded classic
layout (forced_coord_7x7 through hand-overs) and about 6 soups per 256 steps on the held-out levels
(`tests/torch_kitchen/test_scripted.py`). Registered as the architecture "scripted_cook", so it is seated, saved
and loaded like a trained team (it has no weights); `kitchen-eval` seats it beside every team (`partner`).
"""

from __future__ import annotations

import torch
from tensordict.nn import TensorDictModule
from torch import nn

from jax_env import INTERACT, NUM_ACTIONS, STAY, Channel
from jax_env.state import DIR_VECTORS
from torch_kitchen.keys import LOGITS, OBSERVATION, VALUE
from torch_kitchen.models import ActorCritic, register_architecture
from torch_kitchen.models.acting import sampling_actor

UNREACHABLE = 1e4  # a distance longer than any path in a kitchen


def _neighbour(grid: torch.Tensor, direction: int, fill: float) -> torch.Tensor:
    """[N, H, W] -> [N, H, W]: each cell's neighbour in `direction` (DIR_VECTORS order), `fill` outside the grid."""
    dx, dy = DIR_VECTORS[direction]
    padded = nn.functional.pad(grid, (1, 1, 1, 1), value=fill)
    height, width = grid.shape[-2:]
    return padded[..., 1 + dy: 1 + dy + height, 1 + dx: 1 + dx + width]


def _neighbours(grid: torch.Tensor, fill: float) -> torch.Tensor:
    """[N, H, W] -> [N, 4, H, W]: the four neighbours of every cell, in the order of the move actions."""
    return torch.stack([_neighbour(grid, direction, fill) for direction in range(4)], dim=1)


def _beside(targets: torch.Tensor) -> torch.Tensor:
    """bool [..., H, W]: the cells with a target among their four neighbours."""
    height, width = targets.shape[-2:]
    padded = nn.functional.pad(targets, (1, 1, 1, 1))
    return (padded[..., :-2, 1:-1] | padded[..., 2:, 1:-1]) | (padded[..., 1:-1, :-2] | padded[..., 1:-1, 2:])


def distance_from(sources: torch.Tensor, walkable: torch.Tensor) -> torch.Tensor:
    """float [N, H, W]: steps over walkable cells from the nearest walkable source cell (`UNREACHABLE` where
    none can be reached); sources, walkable: bool [N, H, W]. A breadth-first wave, one step per iteration."""
    distance = torch.where(sources & walkable, 0.0, UNREACHABLE)
    blocked = ~walkable
    for _ in range(walkable.shape[-1] * walkable.shape[-2]):
        padded = nn.functional.pad(distance, (1, 1, 1, 1), value=UNREACHABLE)
        closer = torch.minimum(torch.minimum(padded[:, :-2, 1:-1], padded[:, 2:, 1:-1]),
                               torch.minimum(padded[:, 1:-1, :-2], padded[:, 1:-1, 2:])) + 1
        updated = torch.minimum(distance, closer).masked_fill_(blocked, UNREACHABLE)
        if torch.equal(updated, distance):
            break
        distance = updated
    return distance


def distance_to(targets: torch.Tensor, walkable: torch.Tensor) -> torch.Tensor:
    """float [N, H, W]: steps from each walkable cell to the nearest walkable cell beside a target tile
    (`UNREACHABLE` where none can be reached); targets, walkable: bool [N, H, W]."""
    return distance_from(walkable & _beside(targets), walkable)


MOVE_ORDER = "NSEW"  # the move a cook takes where several are equally short: the first of them in this order


class ScriptedCook(nn.Module):
    """uint8 observations [..., 2, H, W, 26] -> logits [..., 2, 6]: each seat's planned action with certainty, or
    uniform logits where it is stuck. `move_order`: its preference among equally short moves, a permutation of
    "NSEW" (cooks with different orders keep different conventions, e.g. which way round a table)."""

    def __init__(self, move_order: str = MOVE_ORDER):
        super().__init__()
        if sorted(move_order) != sorted(MOVE_ORDER):
            raise ValueError(f"move_order must be a permutation of {MOVE_ORDER!r}, got {move_order!r}")
        self.move_order = [MOVE_ORDER.index(direction) for direction in move_order]

    @staticmethod
    def goals(obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, list]:
        """What the cook reads of its kitchens, obs float [N, H, W, C]: where it and its partner stand, the cells
        it may walk, and its goals in order of preference (the tiles to reach [N, H, W], and the action on
        arrival), by what it holds."""
        present = obs > 0  # [N, H, W, C]

        def channel(c):
            return present[..., c]

        me, partner = channel(Channel.SELF), channel(Channel.PARTNER)
        loose = ~(me | partner)  # items on cells where no cook stands lie on counters
        pot = channel(Channel.POT)
        ready_pot = pot & channel(Channel.SOUP)
        cooking_pot = pot & channel(Channel.COOKING_OR_SOUP)
        open_pot = pot & ~channel(Channel.COOKING_OR_SOUP) & (obs[..., Channel.ONIONS_IN_POT] < 3)
        soup_on_counter = channel(Channel.SOUP) & ~pot & loose
        plates = channel(Channel.PLATE_PILE) | (channel(Channel.PLATE) & loose)
        onions = channel(Channel.ONION_PILE) | (channel(Channel.ONION) & loose)
        counter = channel(Channel.EMPTY_COUNTER)
        blocked = pot | counter | channel(Channel.ONION_PILE) | channel(Channel.PLATE_PILE) | channel(Channel.GOAL) | (
            (channel(Channel.SOUP) | channel(Channel.PLATE) | channel(Channel.ONION)) & loose)
        walkable = ~blocked  # the partner moves: it counts only where it is in the way
        # Hand-overs go on counters the partner can reach.
        partner_side = partner | (distance_to(partner, walkable) < UNREACHABLE)
        handover = counter & _beside(partner_side)

        def held(item):
            return (channel(item) & me).flatten(1).any(1)

        partner_has_plate = ((channel(Channel.PLATE) | channel(Channel.SOUP)) & partner).flatten(1).any(1)
        plate_wanted = cooking_pot.flatten(1).any(1) & ~partner_has_plate
        onion_wanted = open_pot.flatten(1).any(1)
        nothing = torch.zeros_like(pot)

        def when(condition, targets):
            return torch.where(condition[:, None, None], targets, nothing)

        # Goals in order of preference, by what the cook holds; the first reachable one is chosen.
        holding_soup, holding_onion, holding_plate = held(Channel.SOUP), held(Channel.ONION), held(Channel.PLATE)
        empty = ~(holding_soup | holding_onion | holding_plate)
        goals = [
            (when(holding_soup, channel(Channel.GOAL)), INTERACT),
            (when(holding_onion, open_pot), INTERACT),
            (when(holding_plate, ready_pot), INTERACT),
            (when(holding_plate, cooking_pot & ~ready_pot), STAY),  # wait beside it until it is done
            (when(~empty, handover), INTERACT),  # put it down where the partner can take it
            (when(empty, soup_on_counter), INTERACT),
            (when(empty & plate_wanted, plates), INTERACT),
            (when(empty & onion_wanted, onions), INTERACT),
            (when(empty, plates), INTERACT),
            (when(empty, onions), INTERACT),
        ]
        return me, partner, walkable, goals

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        batch_shape = observation.shape[:-3]
        obs = observation.reshape(-1, *observation.shape[-3:]).float()  # [N, H, W, C]: one seat's view each
        me, partner, walkable, goals = self.goals(obs)
        targets = torch.stack([targets for targets, _ in goals], dim=1)  # [N, K, H, W]
        n = targets.shape[0]
        # A goal is reachable where a walkable cell beside its tiles is: one wave from the cook serves all goals.
        ends = walkable[:, None] & _beside(targets)  # [N, K, H, W]
        reached = distance_from(me, walkable) < UNREACHABLE
        reachable = (ends & reached[:, None]).flatten(2).any(2)  # [N, K]
        choice = reachable.float().argmax(1)  # the first reachable goal
        pick = choice[:, None, None, None].expand(n, 1, *me.shape[1:])
        goal = targets.gather(1, pick)[:, 0]
        goal_distance = distance_from(ends.gather(1, pick)[:, 0], walkable)
        on_arrival = torch.tensor([action for _, action in goals], device=observation.device)[choice]

        def around_me(grid, fill):  # [N, 4]: the four cells around each cook, in the order of the moves
            return (_neighbours(grid, fill) * me[:, None]).sum((-2, -1))

        def next_step(distance):  # the move towards a lower distance, and whether there is one
            here = (distance * me).sum((-2, -1), keepdim=True)[:, :, 0]
            downhill = around_me(distance, UNREACHABLE) == here - 1
            order = torch.tensor(self.move_order, device=distance.device)
            move = order[downhill[:, order].float().argmax(1)]  # the first downhill move in the cook's order
            return move, (here[:, 0] < UNREACHABLE) & downhill.any(1)

        tile = around_me(goal.float(), 0.0).argmax(1)  # where the goal's tile lies, once beside it
        facing = (obs[..., Channel.SELF_FACING:Channel.SELF_FACING + 4] * me[..., None]).sum((1, 2)).argmax(1)
        arrived = reachable.any(1) & (goal_distance * me).sum((-2, -1)).eq(0)
        step, _ = next_step(goal_distance)
        action = torch.where(arrived, torch.where(facing == tile, on_arrival, tile), step)
        # The partner in the way: half the time a way around it (if any), half the time wait for it to move; where
        # both may step into one cell (the step fails for both), half the time step, half the time wait.
        ahead = around_me(partner.float(), 0.0).gather(1, step[:, None])[:, 0] > 0
        near_partner = partner | _beside(partner)
        contested = ~arrived & ~ahead & (around_me(near_partner.float(), 0.0).gather(1, step[:, None])[:, 0] > 0)
        blocked = ~arrived & ahead
        detour, has_detour = next_step(distance_to(goal, walkable & ~partner))
        detour = torch.where(blocked, detour, action)

        def one_hot(actions):
            return nn.functional.one_hot(actions, NUM_ACTIONS).bool()

        allowed = one_hot(action)
        yielding = contested | (blocked & has_detour)
        allowed = torch.where(yielding[:, None], one_hot(detour) | one_hot(torch.full_like(action, STAY)), allowed)
        allowed |= (~reachable.any(1) | (blocked & ~has_detour))[:, None]  # stuck: any action
        logits = torch.where(allowed, 0.0, -1e9)
        return logits.view(*batch_shape, NUM_ACTIONS)


def scripted_actor_critic() -> ActorCritic:
    """Both seats the scripted cook; its "critic" says 0 everywhere (it learns nothing)."""
    policy = TensorDictModule(ScriptedCook(), in_keys=[OBSERVATION], out_keys=[LOGITS])
    critic = TensorDictModule(
        lambda observation: torch.zeros(*observation.shape[:-3], 1, device=observation.device),
        in_keys=[OBSERVATION], out_keys=[VALUE],
    )  # fmt: skip
    return ActorCritic(actor=sampling_actor(policy), critic=critic, recurrent=False)


SCRIPTED_COOK = "scripted_cook"
register_architecture(SCRIPTED_COOK, lambda obs_shape, hidden, share_params: scripted_actor_critic())
