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

That order is the default convention's (`torch_kitchen.partners.conventions.Convention()`); a convention's preferences
over events reorder the goals, its role holds the other part of the work back, its hand-over habit moves the hand-over
goal, and its temperatures and noise spread the actions. The planning is one pure jittable function,
`jax_env.cook.cook_logits`, with a convention as arrays (`cook_convention`), so the same cook runs inside the kitchens'
XLA programs; `ScriptedCook`, the torch module every partner, teacher and stranger seats, plays through it with
distances read off a table per floor plan kept on the host (`FloorDistances`: one breadth-first wave from each cell,
once per plan, since walls and counters never move).

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

import jax
import numpy as np
import torch
from tensordict.nn import TensorDictModule
from torch import nn

from jax_env import NUM_ACTIONS
from jax_env.cook import CookConvention, cook_logits, walkable_floor
from torch_kitchen.env import jax_device_for
from torch_kitchen.keys import LOGITS, OBSERVATION, VALUE
from torch_kitchen.models import ActorCritic, register_architecture
from torch_kitchen.models.acting import sampling_actor
from torch_kitchen.partners.conventions import MOVE_ORDER, Convention

UNREACHABLE = 1e4  # a distance longer than any path in a kitchen


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


ROLE_PENALTY = 100.0  # a goal off a cook's role scores below every goal on it
PREFERENCE_SCALE = 11.0  # a weight of 1 lifts a goal above the other ten


@dataclass(frozen=True)
class Goal:
    """One goal of the cook's list: the event it leads to and the role it belongs to ("loader", "server" or None
    for both); what it does on arrival beside its tile is `jax_env.cook.ON_ARRIVAL`'s, in the same order."""

    event: str
    role: str | None


# The cook's goals, in order of preference by default; which of them apply depends on what it holds
# (`jax_env.cook.cook_logits`, which takes them in this order).
GOALS = (
    Goal("serve", "server"),  # holding a soup: the serving counter
    Goal("onion_in_pot", "loader"),  # holding an onion: a pot that takes onions
    Goal("soup_pickup", "server"),  # holding a plate: a ready pot
    Goal("soup_pickup", "server"),  # holding a plate: wait beside a cooking pot until it is done
    Goal("counter_place", None),  # holding anything: a counter the partner can reach (a hand-over)
    Goal("serve", "server"),  # empty hands: a soup on a counter
    Goal("plate_pickup", "server"),  # empty: a plate, where a pot cooks and the partner holds none
    Goal("onion_pickup", "loader"),  # empty: an onion, where a pot takes onions
    Goal("plate_pickup", "server"),  # empty: a plate
    Goal("onion_pickup", "loader"),  # empty: an onion
    Goal("idle", None),  # stay where it is: only for a convention with a weight on idling
)
CARRYING = (0, 1, 2, 3)  # the goals of a cook that holds an item: a strict role still finishes what it holds
PRODUCTIVE = (0, 1, 2, 3, 5, 6, 7)  # the goals that bring a soup nearer (not a plate or an onion for later)


def goal_scores(convention: Convention) -> torch.Tensor:
    """float [K]: each goal's score under `convention`; a cook takes the best goal it can reach (or draws one by the
    scores)."""
    scores = []
    strict_wait = convention.strict_role and convention.role != "both" and not convention.weight("idle")
    for rank, goal in enumerate(GOALS):
        score = -rank + PREFERENCE_SCALE * convention.weight(goal.event)
        if goal.event == "idle" and strict_wait:
            score = -ROLE_PENALTY / 2  # waiting, rather than the other role's work
        elif (goal.event == "idle" and not convention.weight("idle")) or (
                goal.event == "counter_place" and convention.handover == "avoid"):
            score = -math.inf  # never taken
        scores.append(score)
    return torch.tensor(scores)


def off_role_penalties(convention: Convention, role: str) -> torch.Tensor:
    """float [K]: what a cook playing `role` takes off each goal's score while its own part of the work waits for it
    (a strict role never off what the cook already holds)."""
    return torch.tensor([ROLE_PENALTY if role != "both" and goal.role not in (None, role)
                         and not (convention.strict_role and rank in CARRYING) else 0.0
                         for rank, goal in enumerate(GOALS)], dtype=torch.float32)


_WALKABLE = jax.jit(walkable_floor)
FEWEST_PLANS = 8  # floor plans the cook's program takes at least (`ScriptedCook.forward`)
_COOK = jax.jit(cook_logits, static_argnames="detour_rows")


def cook_convention(convention: Convention = Convention()) -> CookConvention:
    """The arrays the cook (`jax_env.cook`) plays a convention by: its goals' scores, what a goal off its role loses
    and its own work (as the first cook of the pair, by position or seat, and as the second), its move order,
    temperatures, noise and hand-over habit."""
    roles = convention.roles_of_pair
    off_role = torch.stack([off_role_penalties(convention, role) for role in roles])
    own = [[goal.role == role and i in PRODUCTIVE for i, goal in enumerate(GOALS)] for role in roles]
    return CookConvention(
        scores=goal_scores(convention).numpy(), off_role=off_role.numpy(), own_work=np.array(own),
        move_order=np.array([MOVE_ORDER.index(direction) for direction in convention.move_order], dtype=np.int32),
        goal_temperature=np.float32(convention.goal_temperature),
        move_temperature=np.float32(convention.move_temperature), noise=np.float32(convention.noise),
        prefer_handover=np.bool_(convention.handover == "prefer"), strict_role=np.bool_(convention.strict_role),
        by_seat=np.bool_(convention.by_seat),
    )  # fmt: skip


def stacked_conventions(conventions: list[Convention]) -> CookConvention:
    """The arrays of several conventions, each with a leading dim of the conventions (index them by row to seat a
    convention per row: `ScriptedCook.forward`'s `conventions`)."""
    return CookConvention(*(np.stack(leaves) for leaves in zip(*map(cook_convention, conventions))))


class ScriptedCook(nn.Module):
    """uint8 observations [..., 2, H, W, 26] -> logits [..., 2, 6]: each seat's action distribution under a
    `convention` (the default: its planned action with certainty, a coin flip between a step and a wait where
    the partner may take the cell, uniform where it is stuck), planned by `jax_env.cook` on the JAX device that
    shares the observations' memory, with the floor tables of `FLOOR_DISTANCES`. Any other object than a
    `Convention` is read as a move order, e.g. `ScriptedCook("EWSN")`. Called with `conventions`, arrays with a
    leading dim of the observations' rows (`stacked_conventions(...)` indexed by row), it plays each row's own."""

    def __init__(self, convention: Convention | str = Convention()):
        super().__init__()
        if not isinstance(convention, Convention):
            convention = Convention(move_order=convention)
        self.convention = convention
        self.arrays = cook_convention(convention)

    def forward(self, observation: torch.Tensor, conventions: CookConvention | None = None) -> torch.Tensor:
        batch_shape = observation.shape[:-3]
        views = observation.reshape(-1, *observation.shape[-3:])
        on_cpu = views.device.type == "cpu"
        device = jax_device_for(views.device)
        # Through NumPy on the CPU (a torch tensor's memory may not be aligned as XLA asks), DLPack on a GPU.
        def to_jax(tensor):
            return jax.device_put(tensor.numpy(), device) if on_cpu else jax.dlpack.from_dlpack(tensor.contiguous())

        kitchens = to_jax(views.contiguous())
        tables, plan = FLOOR_DISTANCES(torch.from_dlpack(_WALKABLE(kitchens)).to(views.device))
        # The floor plans padded to a power of two, at least `FEWEST_PLANS`: one compilation serves batches of any
        # number of plans up to it (the few kitchens of a study's games stepped together).
        plans = max(FEWEST_PLANS, 1 << (len(tables) - 1).bit_length())
        tables = nn.functional.pad(tables, (0, 0, 0, 0, 0, plans - len(tables)), value=UNREACHABLE)
        # On a CPU the waves around a partner in the way run for the quarter of the rows that meet theirs at most (a
        # branch the host reads, which a GPU would wait on: there every row's).
        logits = _COOK(kitchens, self.arrays if conventions is None else conventions, to_jax(tables),
                       to_jax(plan.int()), detour_rows=max(1, len(views) // 4) if on_cpu else None)
        return torch.from_dlpack(logits).to(views.device).view(*batch_shape, NUM_ACTIONS)


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
