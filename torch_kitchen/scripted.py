"""A scripted cook: a partner no team trained with, reading the same observation a trained agent reads.

It plans on the kitchen it sees, on any layout: it weighs the goals of a short list (what it holds and what the
pots need decide which apply), takes the best one it can reach (or draws one, by a convention's temperature), walks
a shortest path to a cell beside the goal's tile, faces the tile and interacts. Where the partner stands in its way
it takes a way around the partner or waits, at random, and where both could step into one cell it steps or waits at
random: this breaks the symmetry of two cooks meeting in a corridor.

    holding a soup    the serving counter; else a counter the partner can reach (a hand-over)
    holding an onion  a pot that takes onions; else a hand-over
    holding a plate   a ready pot; else wait beside a cooking pot; else a hand-over
    empty hands       a soup on a counter; a plate if a pot cooks and the partner holds no plate; an onion if a
                      pot takes onions; then a plate, then an onion (from a pile or a counter)

That order is the default convention's (`torch_kitchen.conventions.Convention()`); a convention's preferences over
events reorder the goals, its role holds the other part of the work back, its hand-over habit moves the hand-over
goal, and its temperatures and noise spread the actions. Distances are read off a table per floor plan
(`FloorDistances`): one breadth-first wave from each cell, once per kitchen, since walls and counters never move.

Where nothing on its list is reachable it picks an action at random. Two of it deliver on every expanded classic
layout (forced_coord_7x7 through hand-overs) and about 6 soups per 256 steps on the held-out levels
(`tests/torch_kitchen/test_scripted.py`). Registered as the architecture "scripted_cook" (its convention a model
option), so it is seated, saved and loaded like a trained team (it has no weights); `kitchen-eval` seats it beside
every team (`partner`), and the zoo's cooks as strangers (`trainers.zoo`).
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass

import numpy as np
import torch
from tensordict.nn import TensorDictModule
from torch import nn

from jax_env import INTERACT, NUM_ACTIONS, STAY, Channel
from jax_env.cook import CookConvention
from jax_env.state import DIR_VECTORS
from torch_kitchen.conventions import MOVE_ORDER, Convention
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


class FloorDistances:
    """Steps between every two cells of a kitchen over its floor. A kitchen's walls, counters, piles and pots never
    move (items lie on counters), so the table of a floor plan is computed once, a breadth-first wave from each of
    its cells, and kept (the last `capacity` plans, per device); cooks then read distances as rows of it."""

    def __init__(self, capacity: int = 4096):
        self.capacity = capacity
        self._tables: OrderedDict[tuple, torch.Tensor] = OrderedDict()

    def __call__(self, walkable: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The tables of the floor plans of walkable bool [N, H, W], float [P, H * W, H * W] (row c: the steps from
        cell c, a flat index, to every cell; `UNREACHABLE` from or to a cell off the floor or cut off from it), and
        each kitchen's plan long [N]."""
        n, height, width = walkable.shape
        plans, inverse = np.unique(np.packbits(walkable.flatten(1).cpu().numpy(), axis=1), axis=0,
                                   return_inverse=True)
        keys = [(plan.tobytes(), height, width, str(walkable.device)) for plan in plans]
        missing = [i for i, key in enumerate(keys) if key not in self._tables]
        if missing:
            cells = height * width
            floors = np.unpackbits(plans[missing], axis=1, count=cells).astype(bool)
            floors = torch.as_tensor(floors, device=walkable.device).view(-1, 1, height, width)
            starts = torch.eye(cells, dtype=torch.bool, device=walkable.device).view(1, cells, height, width)
            floors, starts = torch.broadcast_tensors(floors, starts)
            computed = distance_from(starts.flatten(0, 1), floors.flatten(0, 1)).view(len(missing), cells, cells)
            for i, table in zip(missing, computed):
                self._tables[keys[i]] = table
        for key in keys:
            self._tables.move_to_end(key)
        tables = torch.stack([self._tables[key] for key in keys])
        while len(self._tables) > self.capacity:
            self._tables.popitem(last=False)
        return tables, torch.as_tensor(inverse.reshape(-1), device=walkable.device)


FLOOR_DISTANCES = FloorDistances()  # every cook's: the floor plans seen in this process


def distance_rows(tables: torch.Tensor, plan: torch.Tensor, cells: torch.Tensor) -> torch.Tensor:
    """float [N, ..., H * W]: the steps from the cell of each bool mask cells [N, ..., H, W] (one cell at most) to
    every cell, read off the floor tables (`FloorDistances`); `UNREACHABLE` where a mask is empty."""
    flat = cells.flatten(-2)
    index = flat.float().argmax(-1)  # [N, ...]
    row = plan.view(-1, *[1] * (index.ndim - 1)) * tables.shape[1] + index
    rows = tables.flatten(0, 1)[row]
    return torch.where(flat.any(-1, keepdim=True), rows, UNREACHABLE)


OPPOSITE = (1, 0, 3, 2)  # the direction opposite each of NORTH, SOUTH, EAST, WEST
ROLE_PENALTY = 100.0  # a goal off a cook's role scores below every goal on it
PREFERENCE_SCALE = 11.0  # a weight of 1 lifts a goal above the other ten


def _shifted(grid: torch.Tensor, direction: int) -> torch.Tensor:
    """[N, H, W] -> [N, H, W]: the cells one step in `direction` from each True cell of `grid`."""
    return _neighbour(grid, OPPOSITE[direction], False)


@dataclass(frozen=True)
class Goal:
    """One goal of the cook's list: the event it leads to, the role it belongs to ("loader", "server" or None
    for both), and the action on arrival beside its tile."""

    event: str
    role: str | None
    on_arrival: int


# The cook's goals, in order of preference by default; which of them apply depends on what it holds (`goals`).
GOALS = (
    Goal("serve", "server", INTERACT),  # holding a soup: the serving counter
    Goal("onion_in_pot", "loader", INTERACT),  # holding an onion: a pot that takes onions
    Goal("soup_pickup", "server", INTERACT),  # holding a plate: a ready pot
    Goal("soup_pickup", "server", STAY),  # holding a plate: wait beside a cooking pot until it is done
    Goal("counter_place", None, INTERACT),  # holding anything: a counter the partner can reach (a hand-over)
    Goal("serve", "server", INTERACT),  # empty hands: a soup on a counter
    Goal("plate_pickup", "server", INTERACT),  # empty: a plate, where a pot cooks and the partner holds none
    Goal("onion_pickup", "loader", INTERACT),  # empty: an onion, where a pot takes onions
    Goal("plate_pickup", "server", INTERACT),  # empty: a plate
    Goal("onion_pickup", "loader", INTERACT),  # empty: an onion
    Goal("idle", None, STAY),  # stay where it is: only for a convention with a weight on idling
)
IDLE, HANDOVER = len(GOALS) - 1, 4
PRODUCTIVE = (0, 1, 2, 3, 5, 6, 7)  # the goals that bring a soup nearer (not a plate or an onion for later)


def goal_scores(convention: Convention) -> tuple[torch.Tensor, torch.Tensor]:
    """float [K], [K]: each goal's score under `convention`, and what its role takes off the score while the cook's
    own part of the work waits for it; a cook takes the best goal it can reach (or draws one by the scores)."""
    scores, off_role = [], []
    for rank, goal in enumerate(GOALS):
        score = -rank + PREFERENCE_SCALE * convention.weight(goal.event)
        if (goal.event == "idle" and not convention.weight("idle")) or (
                goal.event == "counter_place" and convention.handover == "avoid"):
            score = -math.inf  # never taken
        scores.append(score)
        off_role.append(ROLE_PENALTY if convention.role != "both" and goal.role not in (None, convention.role) else 0)
    return torch.tensor(scores), torch.tensor(off_role, dtype=torch.float32)


class ScriptedCook(nn.Module):
    """uint8 observations [..., 2, H, W, 26] -> logits [..., 2, 6]: each seat's action distribution under a
    `convention` (the default: its planned action with certainty, a coin flip between a step and a wait where
    the partner may take the cell, uniform where it is stuck). Any other object than a `Convention` is read as a
    move order, e.g. `ScriptedCook("EWSN")`."""

    def __init__(self, convention: Convention | str = Convention()):
        super().__init__()
        if not isinstance(convention, Convention):
            convention = Convention(move_order=convention)
        self.convention = convention
        self.move_order = [MOVE_ORDER.index(direction) for direction in convention.move_order]
        scores, off_role = goal_scores(convention)
        self.register_buffer("scores", scores, persistent=False)
        self.register_buffer("off_role", off_role, persistent=False)
        own = [goal.role == convention.role for goal in GOALS]
        # The goals that move the cook's own part of the work on: while one is in reach, goals off its role wait.
        self.register_buffer("own_work", torch.tensor([mine and i in PRODUCTIVE for i, mine in enumerate(own)]),
                             persistent=False)

    @staticmethod
    def goals(obs: torch.Tensor, floor: FloorDistances) -> tuple[torch.Tensor, ...]:
        """What the cook reads of its kitchens, obs float [N, H, W, C]: where it and its partner stand, the cells
        it may walk, the tiles of each of `GOALS` where it applies (bool [N, K, H, W]: none where it does not, by
        what the cook holds), whether the partner's hands are empty [N], and the kitchens' floor tables and plans
        (`FloorDistances`)."""
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
        tables, plan = floor(walkable)
        # Hand-overs go on counters the partner can reach.
        partner_side = partner | (distance_rows(tables, plan, partner) < UNREACHABLE).view_as(partner)
        handover = counter & _beside(partner_side)

        def held(item, who=me):
            return (channel(item) & who).flatten(1).any(1)

        partner_empty = ~(held(Channel.PLATE, partner) | held(Channel.SOUP, partner) | held(Channel.ONION, partner))
        partner_has_plate = ((channel(Channel.PLATE) | channel(Channel.SOUP)) & partner).flatten(1).any(1)
        plate_wanted = cooking_pot.flatten(1).any(1) & ~partner_has_plate
        onion_wanted = open_pot.flatten(1).any(1)
        nothing = torch.zeros_like(pot)

        def when(condition, targets):
            return torch.where(condition[:, None, None], targets, nothing)

        holding_soup, holding_onion, holding_plate = held(Channel.SOUP), held(Channel.ONION), held(Channel.PLATE)
        empty = ~(holding_soup | holding_onion | holding_plate)
        targets = torch.stack([
            when(holding_soup, channel(Channel.GOAL)),
            when(holding_onion, open_pot),
            when(holding_plate, ready_pot),
            when(holding_plate, cooking_pot & ~ready_pot),
            when(~empty, handover),
            when(empty, soup_on_counter),
            when(empty & plate_wanted, plates),
            when(empty & onion_wanted, onions),
            when(empty, plates),
            when(empty, onions),
            nothing,  # idling needs no tile
        ], dim=1)  # fmt: skip
        return me, partner, walkable, targets, partner_empty, tables, plan

    def forward(self, observation: torch.Tensor) -> torch.Tensor:
        batch_shape = observation.shape[:-3]
        obs = observation.reshape(-1, *observation.shape[-3:]).float()  # [N, H, W, C]: one seat's view each
        me, partner, walkable, targets, partner_empty, tables, plan = self.goals(obs, FLOOR_DISTANCES)
        n, k = targets.shape[:2]
        device = observation.device
        # Steps to every goal from the cook's cell and from each cell around it, with the partner in the way or not
        # (a way around it, where the partner stands beside the cook: elsewhere it is never asked for).
        starts = torch.stack([me, *(_shifted(me, direction) for direction in range(4))], dim=1)  # [N, 5, H, W]
        ends = (walkable[:, None] & _beside(targets)).flatten(2)  # [N, K, H * W]: where a cook stands to reach a goal
        free = distance_rows(tables, plan, starts)  # [N, 5, H * W]
        steps = torch.where(ends[:, :, None], free[:, None], UNREACHABLE).amin(-1)  # [N, K, 5]
        detours = steps.clone()
        beside_partner = (starts[:, 1:] & partner[:, None]).flatten(1).any(1)
        if beside_partner.any():
            rows = beside_partner.nonzero()[:, 0]
            open_floor = (walkable & ~partner)[rows]
            around = distance_from(starts[rows].flatten(0, 1), open_floor.repeat_interleave(5, 0))
            around = around.view(len(rows), 1, 5, -1)
            detours[rows] = torch.where(ends[rows][:, :, None], around, UNREACHABLE).amin(-1)
        here, next_cells = steps[..., 0], steps[..., 1:]  # [N, K], [N, K, 4]
        reachable = here < UNREACHABLE
        reachable[:, IDLE] = True

        # Which goal: the best one it can reach, or one drawn by its score; a loader leaves plates and soups while an
        # onion can go in a pot, a server onions while a plate or a soup can be taken.
        busy = (reachable & self.own_work).any(1, keepdim=True)
        scores = torch.where(reachable, self.scores - busy * self.off_role, -math.inf)
        temperature = self.convention.goal_temperature
        if temperature > 0:
            goal_weights = torch.softmax(scores / temperature, 1)
        else:
            goal_weights = nn.functional.one_hot(scores.argmax(1), k).float()
        goal_weights = torch.where(torch.isinf(scores).all(1, keepdim=True), 0.0, goal_weights)
        if self.convention.handover == "prefer":
            goal_weights = self.prefer_handover(goal_weights, here, reachable, ends, partner_empty,
                                                distance_rows(tables, plan, partner))

        # For each goal, the action towards it.
        order = torch.tensor(self.move_order, device=device)

        def first_downhill(here, next_cells):  # [N, K]: the first move in the cook's order that gets nearer
            downhill = next_cells == here[..., None] - 1
            return order[downhill[..., order].float().argmax(-1)], (here < UNREACHABLE) & downhill.any(-1)

        def around_me(grid):  # [N, 4] of any [N, H, W]: the four cells around each cook, in the order of the moves
            return (_neighbours(grid.float(), 0.0) * me[:, None]).sum((-2, -1))

        step, _ = first_downhill(here, next_cells)
        tiles_around = torch.einsum("nkc,ndc->nkd", targets.flatten(2).float(),
                                    torch.stack([_shifted(me, d) for d in range(4)], 1).flatten(2).float())
        tile = tiles_around.argmax(-1)  # [N, K]: where the goal's tile lies, once beside it
        facing = (obs[..., Channel.SELF_FACING:Channel.SELF_FACING + 4] * me[..., None]).sum((1, 2)).argmax(1)
        arrived = reachable & here.eq(0)
        on_arrival = torch.tensor([goal.on_arrival for goal in GOALS], device=device).expand(n, k)
        action = torch.where(arrived, torch.where(facing[:, None] == tile, on_arrival, tile), step)
        action[:, IDLE] = STAY
        # The partner in the way: half the time a way around it (if any), half the time wait for it to move; where
        # both may step into one cell (the step fails for both), half the time step, half the time wait.
        ahead = around_me(partner).gather(1, step) > 0
        contested = ~arrived & ~ahead & (around_me(partner | _beside(partner)).gather(1, step) > 0)
        blocked = ~arrived & ahead
        detour, has_detour = first_downhill(detours[..., 0], detours[..., 1:])
        detour = torch.where(blocked, detour, action)

        def one_hot(actions):
            return nn.functional.one_hot(actions, NUM_ACTIONS).bool()

        moving = ~arrived
        moving[:, IDLE] = False
        allowed = one_hot(action)  # [N, K, 6]
        yielding = (contested | (blocked & has_detour)) & moving
        allowed = torch.where(yielding[..., None], one_hot(detour) | one_hot(torch.full_like(action, STAY)), allowed)
        allowed |= (blocked & ~has_detour & moving)[..., None]  # stuck: any action
        chances = allowed.float() / allowed.sum(-1, keepdim=True)
        if self.convention.move_temperature > 0:
            chances = torch.where((moving & reachable)[..., None], self.boltzmann_moves(detours, chances), chances)

        probs = (goal_weights[..., None] * chances).sum(1)  # [N, 6]
        probs = torch.where(goal_weights.sum(1, keepdim=True) > 0, probs, 1.0 / NUM_ACTIONS)  # nothing to do
        if self.convention.noise > 0:
            probs = (1 - self.convention.noise) * probs + self.convention.noise / NUM_ACTIONS
        # Logits with the likeliest action at 0: a certain plan is 0 / -1e9, as a team's logits can be read.
        logits = torch.where(probs > 0, probs.log() - probs.amax(-1, keepdim=True).log(), -1e9)
        return logits.view(*batch_shape, NUM_ACTIONS)

    def boltzmann_moves(self, steps_around: torch.Tensor, planned: torch.Tensor) -> torch.Tensor:
        """[N, K, 6]: moves drawn by the steps left after each (the partner's cell closed), a wait where no move
        is open; steps_around [N, K, 5] from the cook's cell and the four around it."""
        here, after = steps_around[..., :1], steps_around[..., 1:]
        open_moves = after < UNREACHABLE
        logits = torch.where(open_moves, -(after - here) / self.convention.move_temperature, -math.inf)
        moves = torch.softmax(torch.where(open_moves.any(-1, keepdim=True), logits, 0.0), -1)
        chances = torch.cat([moves, torch.zeros_like(planned[..., 4:])], -1)
        return torch.where(open_moves.any(-1, keepdim=True), chances, planned)

    @staticmethod
    def prefer_handover(goal_weights, here, reachable, ends, partner_empty, from_partner):
        """A cook that prefers hand-overs puts its item on a counter the partner can reach where the partner's hands
        are empty and the partner stands nearer the goal the cook carries it to; from_partner [N, H * W]: the steps
        from the partner's cell."""
        partner_steps = torch.where(ends, from_partner[:, None], UNREACHABLE).amin(-1)  # [N, K]
        carried = goal_weights[:, :HANDOVER].argmax(1, keepdim=True)  # the goal of the item it holds, if any
        carrying = goal_weights[:, :HANDOVER].sum(1) > 0
        nearer = partner_steps.gather(1, carried)[:, 0] + 1 < here.gather(1, carried)[:, 0]
        hand_over = carrying & nearer & partner_empty & reachable[:, HANDOVER]
        return torch.where(hand_over[:, None], nn.functional.one_hot(torch.full_like(carried[:, 0], HANDOVER),
                                                                     goal_weights.shape[1]).float(), goal_weights)


def cook_convention(convention: Convention = Convention()) -> CookConvention:
    """The arrays of `jax_env.cook` for a convention: what `ScriptedCook` derives from it, as numpy values."""
    cook = ScriptedCook(convention)
    return CookConvention(
        scores=cook.scores.numpy(), off_role=cook.off_role.numpy(), own_work=cook.own_work.numpy(),
        move_order=np.array(cook.move_order, dtype=np.int32), goal_temperature=np.float32(convention.goal_temperature),
        move_temperature=np.float32(convention.move_temperature), noise=np.float32(convention.noise),
        prefer_handover=np.bool_(convention.handover == "prefer"),
    )  # fmt: skip


def scripted_actor_critic(convention: Convention = Convention()) -> ActorCritic:
    """Both seats the scripted cook of `convention`; its "critic" says 0 everywhere (it learns nothing)."""
    policy = TensorDictModule(ScriptedCook(convention), in_keys=[OBSERVATION], out_keys=[LOGITS])
    critic = TensorDictModule(
        lambda observation: torch.zeros(*observation.shape[:-3], 1, device=observation.device),
        in_keys=[OBSERVATION], out_keys=[VALUE],
    )  # fmt: skip
    return ActorCritic(actor=sampling_actor(policy), critic=critic, recurrent=False)


SCRIPTED_COOK = "scripted_cook"
register_architecture(SCRIPTED_COOK, lambda obs_shape, hidden, share_params, convention=None: scripted_actor_critic(
    Convention.from_dict(convention) if convention else Convention()))
