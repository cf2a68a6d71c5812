"""Solvability of a kitchen: can the two agents, between them, cook and deliver one soup?

The checker reasons about where items can go, not about timing. It knows nothing of how a level was made.

Model
-----
- Each agent walks on the floor cells it can reach from its start cell (4-neighbourhood flood fill): its
  *region*. It can *use* every non-floor cell (pile, pot, goal, counter) that is a 4-neighbour of its region.
- A *hand-over counter* is a plain COUNTER both agents can use. An agent puts an item down there and the other
  picks it up; one such counter serves any number of hand-overs, one after another.
- An item kind is *available* to an agent when the agent can come to hold it:
    onion  - the agent uses an onion pile, or onions are available to the other agent and a hand-over
             counter exists;
    plate  - the same with plate piles;
    dish   - the agent uses a pot that can be *filled* (some agent holding onions uses it) and plates are
             available to the agent; or a dish is available to the other agent and a hand-over counter exists.
  The plate must go to the pot that received the onions, so fillable pots are tracked cell by cell. A pot both
  agents use is itself a meeting point: one fills it, the other serves it.
- The level is solvable when some agent to which a dish is available uses a goal.
  With two agents one hand-over per item is enough: holding an item is all that matters (an agent's region is
  connected), and a hand-over counter is usable by both, so passing an item back never gains anything.

Classes
-------
    SOLO (1)                 one agent uses an onion pile, a pot, a plate pile and a goal: it can do the
                             whole task alone.
    FORCED_COORDINATION (2)  solvable, but neither agent can do it alone: items must pass between them.
    UNSOLVABLE (0)           no soup can be delivered.

Limits: agents blocking each other in a corridor and the time needed are ignored; both only matter when the
agents share a region, where either agent reaches everything the other does.

Everything is numpy. `analyse_levels` is the one implementation: it floods a whole batch at once by iterative
dilation of boolean masks until no mask grows; the single-level functions call it on a batch of one.
"""

from __future__ import annotations

import dataclasses
from typing import NamedTuple

import numpy as np

from jax_env.layouts import COUNTER, FLOOR, GOAL, NUM_CELL_KINDS, ONION_PILE, PLATE_PILE, POT, Layout

UNSOLVABLE, SOLO, FORCED_COORDINATION = 0, 1, 2
CLASS_NAMES = ("unsolvable", "solo", "forced_coordination")

_KIND_NAMES = {ONION_PILE: "onion pile", PLATE_PILE: "plate pile", POT: "pot", GOAL: "goal"}


class LevelAnalysis(NamedTuple):
    """The item-flow analysis of a batch of N levels of shape (H, W); agent axis of size 2, agent 0 first.

    region:     bool (N, 2, H, W)  floor cells each agent can reach.
    usable:     bool (N, 2, H, W)  non-floor cells each agent can use (4-neighbours of its region).
    handover:   bool (N, H, W)     plain counters both agents can use.
    uses_kind:  bool (N, 2, K)     whether each agent uses some cell of each kind (K = NUM_CELL_KINDS).
    onion:      bool (N, 2)        onions available to each agent (own pile or via a hand-over).
    plate:      bool (N, 2)        plates available to each agent.
    fillable:   bool (N, H, W)     pots some agent holding onions can use.
    serves:     bool (N, 2, H, W)  fillable pots each agent can also bring a plate to (dish taken there).
    dish:       bool (N, 2)        dishes available to each agent.
    delivers:   bool (N, 2)        each agent can hold a dish and uses a goal.
    solo:       bool (N, 2)        each agent uses an onion pile, a pot, a plate pile and a goal.
    codes:      int8 (N,)          UNSOLVABLE, SOLO or FORCED_COORDINATION.
    """

    region: np.ndarray
    usable: np.ndarray
    handover: np.ndarray
    uses_kind: np.ndarray
    onion: np.ndarray
    plate: np.ndarray
    fillable: np.ndarray
    serves: np.ndarray
    dish: np.ndarray
    delivers: np.ndarray
    solo: np.ndarray
    codes: np.ndarray


def _dilate(mask: np.ndarray) -> np.ndarray:
    """The mask grown by one step in the 4-neighbourhood over its last two axes (bool, any leading shape)."""
    grown = mask.copy()
    grown[..., 1:, :] |= mask[..., :-1, :]
    grown[..., :-1, :] |= mask[..., 1:, :]
    grown[..., :, 1:] |= mask[..., :, :-1]
    grown[..., :, :-1] |= mask[..., :, 1:]
    return grown


def _check_batch(grids: np.ndarray, agent_cells: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    grids = np.asarray(grids)
    agent_cells = np.asarray(agent_cells)
    if grids.ndim != 3:
        raise ValueError(f"grids must have shape (N, H, W), got {grids.shape}")
    if not np.issubdtype(grids.dtype, np.integer):
        raise ValueError(f"grids must hold integer cell kinds, got dtype {grids.dtype}")
    if agent_cells.shape != (grids.shape[0], 2, 2):
        raise ValueError(f"agent_cells must have shape (N, 2, 2) = ({grids.shape[0]}, 2, 2), got {agent_cells.shape}")
    height, width = grids.shape[1:]
    xs, ys = agent_cells[..., 0].astype(np.int64), agent_cells[..., 1].astype(np.int64)
    inside = (xs >= 0) & (xs < width) & (ys >= 0) & (ys < height)
    if not inside.all():
        level, agent = np.argwhere(~inside)[0]
        raise ValueError(
            f"level {level}: agent {agent} starts at (x, y) = {tuple(agent_cells[level, agent])}, "
            f"outside the {height}x{width} grid"
        )
    levels = np.arange(grids.shape[0])[:, None]
    on_floor = grids[levels, ys, xs] == FLOOR
    if not on_floor.all():
        level, agent = np.argwhere(~on_floor)[0]
        raise ValueError(
            f"level {level}: agent {agent} starts at (x, y) = {tuple(agent_cells[level, agent])}, "
            "which is not a floor cell"
        )
    return grids, agent_cells.astype(np.int64)


def analyse_levels(grids: np.ndarray, agent_cells: np.ndarray) -> LevelAnalysis:
    """Analyse the item flow of a batch of levels.

    grids: integer (N, H, W) cell kinds; agent_cells: integer (N, 2, 2) start cells as (x, y), agent 0 first.
    Returns a `LevelAnalysis` of numpy arrays. Raises `ValueError` on bad shapes or a start cell off the floor.
    """
    grids, agent_cells = _check_batch(grids, agent_cells)
    n, height, width = grids.shape
    floor = (grids == FLOOR)[:, None]

    region = np.zeros((n, 2, height, width), dtype=bool)
    region[np.arange(n)[:, None], np.arange(2)[None, :], agent_cells[..., 1], agent_cells[..., 0]] = True
    # A shortest path visits each floor cell at most once, so H * W steps always reach the fixed point.
    for _ in range(height * width):
        grown = _dilate(region) & floor
        if np.array_equal(grown, region):
            break
        region = grown

    usable = _dilate(region) & ~floor
    kinds = grids[:, None]
    uses_kind = np.stack([(usable & (kinds == k)).any(axis=(-2, -1)) for k in range(NUM_CELL_KINDS)], axis=-1)
    handover = usable[:, 0] & usable[:, 1] & (grids == COUNTER)
    can_hand_over = handover.any(axis=(-2, -1))[:, None]

    def hand_over(own: np.ndarray) -> np.ndarray:
        # Two agents: a counter both use passes an item either way.
        return own | (can_hand_over & own.any(axis=1, keepdims=True))

    onion = hand_over(uses_kind[..., ONION_PILE])
    plate = hand_over(uses_kind[..., PLATE_PILE])
    uses_pot = usable & (kinds == POT)
    fillable = (uses_pot & onion[:, :, None, None]).any(axis=1)
    serves = uses_pot & fillable[:, None] & plate[:, :, None, None]
    dish = hand_over(serves.any(axis=(-2, -1)))
    delivers = dish & uses_kind[..., GOAL]
    solo = uses_kind[..., ONION_PILE] & uses_kind[..., PLATE_PILE] & uses_kind[..., POT] & uses_kind[..., GOAL]

    codes = np.where(solo.any(axis=1), SOLO, np.where(delivers.any(axis=1), FORCED_COORDINATION, UNSOLVABLE))
    return LevelAnalysis(
        region=region,
        usable=usable,
        handover=handover,
        uses_kind=uses_kind,
        onion=onion,
        plate=plate,
        fillable=fillable,
        serves=serves,
        dish=dish,
        delivers=delivers,
        solo=solo,
        codes=codes.astype(np.int8),
    )


def classify_levels(grids: np.ndarray, agent_cells: np.ndarray) -> np.ndarray:
    """Class codes of a batch of levels.

    grids: integer (N, H, W) cell kinds; agent_cells: integer (N, 2, 2) start cells as (x, y).
    Returns int8 (N,): UNSOLVABLE (0), SOLO (1) or FORCED_COORDINATION (2); names in `CLASS_NAMES`.
    """
    return analyse_levels(grids, agent_cells).codes


def _cells(mask: np.ndarray) -> tuple[tuple[int, int], ...]:
    """(x, y) cells of a bool (H, W) mask, row-major."""
    return tuple((int(x), int(y)) for y, x in np.argwhere(mask))


def _fmt(cells: tuple[tuple[int, int], ...]) -> str:
    return ", ".join(f"({x}, {y})" for x, y in cells) if cells else "none"


@dataclasses.dataclass(frozen=True, eq=False)
class LevelReport:
    """Why one level is solo, forced-coordination or unsolvable. Cells are (x, y); agent axis of size 2.

    grid:         uint8 (H, W) cell kinds.
    agent_cells:  the agents' start cells, agent 0 first.
    region:       bool (2, H, W) floor cells each agent can reach.
    usable:       bool (2, H, W) non-floor cells each agent can use.
    handover:     bool (H, W) plain counters both agents can use.
    onion, plate, dish: bool (2,) whether each agent can come to hold that item (hand-overs included).
    fillable:     bool (H, W) pots that can receive onions.
    serves:       bool (2, H, W) fillable pots each agent can bring a plate to.
    delivers:     bool (2,) whether each agent can hold a dish at a goal.
    solo:         bool (2,) whether each agent can do the whole task alone.
    level_class:  "solo", "forced_coordination" or "unsolvable".
    """

    grid: np.ndarray
    agent_cells: tuple[tuple[int, int], tuple[int, int]]
    region: np.ndarray
    usable: np.ndarray
    handover: np.ndarray
    onion: np.ndarray
    plate: np.ndarray
    dish: np.ndarray
    fillable: np.ndarray
    serves: np.ndarray
    delivers: np.ndarray
    solo: np.ndarray
    level_class: str

    @property
    def solvable(self) -> bool:
        return self.level_class != "unsolvable"

    @property
    def shared_region(self) -> bool:
        """True when both agents stand in the same floor region."""
        return bool((self.region[0] & self.region[1]).any())

    @property
    def handover_counters(self) -> tuple[tuple[int, int], ...]:
        """Plain counters both agents can use, as (x, y)."""
        return _cells(self.handover)

    def usable_cells(self, agent: int, kind: int) -> tuple[tuple[int, int], ...]:
        """The (x, y) cells of one kind (ONION_PILE, PLATE_PILE, POT, GOAL, COUNTER) that `agent` can use."""
        return _cells(self.usable[agent] & (self.grid == kind))

    def _uses(self, agent: int, kind: int) -> bool:
        return bool((self.usable[agent] & (self.grid == kind)).any())

    def _summary(self, agent: int) -> str:
        kinds = (ONION_PILE, POT, PLATE_PILE, GOAL)
        used = [_KIND_NAMES[k] for k in kinds if self._uses(agent, k)]
        missing = [_KIND_NAMES[k] for k in kinds if not self._uses(agent, k)]
        text = f"agent {agent} uses " + (", ".join(used) if used else "no pile, pot or goal")
        return text + (f" (no {', no '.join(missing)})" if used and missing else "")

    def _lacks(self, agent: int, source: str, have: np.ndarray) -> str:
        """Why `agent` cannot come to hold an item whose source it does not use."""
        if have[1 - agent]:
            return f"it uses no {source} and no hand-over counter connects it to agent {1 - agent}"
        return f"it uses no {source}"

    def _why_unsolvable(self) -> str:
        # Follow the soup's path and report the first step no agent can make.
        if not self.onion.any():
            return "neither agent can reach an onion pile"
        if not self.fillable.any():
            if not (self._uses(0, POT) or self._uses(1, POT)):
                return "no pot can receive onions: neither agent can reach a pot"
            parts = []
            for a in (0, 1):
                pots = self.usable_cells(a, POT)
                if self.onion[a]:
                    parts.append(f"agent {a} can get onions but cannot reach any pot")
                elif pots:
                    reason = self._lacks(a, "onion pile", self.onion)
                    parts.append(f"agent {a} reaches pots at {_fmt(pots)} but cannot get onions: {reason}")
                else:
                    parts.append(f"agent {a} reaches neither an onion pile nor a pot")
            return "no pot can receive onions: " + "; ".join(parts)
        if not self.plate.any():
            return "neither agent can reach a plate pile"
        if not self.serves.any():
            parts = []
            for a in (0, 1):
                pots = _cells(self.usable[a] & self.fillable)
                if self.plate[a]:
                    parts.append(f"agent {a} can get plates but reaches none of these pots")
                elif pots:
                    reason = self._lacks(a, "plate pile", self.plate)
                    parts.append(f"agent {a} reaches {_fmt(pots)} but cannot get a plate: {reason}")
                else:
                    parts.append(f"agent {a} can get no plate and reaches none of these pots")
            fillable = _fmt(_cells(self.fillable))
            return f"no pot that can receive onions ({fillable}) can also get a plate: " + "; ".join(parts)
        if not (self._uses(0, GOAL) or self._uses(1, GOAL)):
            return "neither agent can reach a goal"
        parts = []
        for a in (0, 1):
            goals = self.usable_cells(a, GOAL)
            if self.dish[a]:
                parts.append(f"agent {a} can get a dish but cannot reach any goal")
            elif goals:
                reason = (
                    f"no hand-over counter connects it to agent {1 - a}"
                    if self.dish[1 - a]
                    else "no dish can be made within its reach"
                )
                parts.append(f"agent {a} reaches goals at {_fmt(goals)} but cannot get a dish: {reason}")
            else:
                parts.append(f"agent {a} can get no dish and reaches no goal")
        return "no dish can reach a goal: " + "; ".join(parts)

    def explain(self) -> str:
        """A human-readable account of the class: who can do what, and what breaks when unsolvable."""
        if self.shared_region:
            where = "agents 0 and 1 share one floor region"
        else:
            where = f"agents 0 and 1 are in separate floor regions; hand-over counters: {_fmt(self.handover_counters)}"
        reach = f"{self._summary(0)}; {self._summary(1)}"
        if self.level_class == "solo":
            who = "agents 0 and 1 each" if self.solo.all() else f"agent {int(np.argmax(self.solo))}"
            head = f"solo: {who} can reach an onion pile, a pot, a plate pile and a goal alone"
        elif self.level_class == "forced_coordination":
            dish_pots = _fmt(_cells(self.serves.any(axis=0)))
            head = (
                f"forced coordination: neither agent can do the task alone; items must pass between them "
                f"(soup can be cooked in pots {dish_pots})"
            )
        else:
            head = "unsolvable: " + self._why_unsolvable()
        return f"{head}. {where}. {reach}."


def _batch_of_one(grid: np.ndarray, agent_cells) -> tuple[np.ndarray, np.ndarray]:
    grid = np.asarray(grid)
    cells = np.asarray(agent_cells, dtype=np.int64)
    if grid.ndim != 2:
        raise ValueError(f"grid must have shape (H, W), got {grid.shape}")
    if cells.shape != (2, 2):
        raise ValueError(f"agent_cells must be two (x, y) pairs, got shape {cells.shape}")
    return grid[None], cells[None]


def analyse_level(grid: np.ndarray, agent_cells) -> LevelReport:
    """Analyse one level. grid: integer (H, W) cell kinds; agent_cells: ((x, y), (x, y)), agent 0 first."""
    grids, cells = _batch_of_one(grid, agent_cells)
    batch = analyse_levels(grids, cells)
    return LevelReport(
        grid=grids[0].astype(np.uint8),
        agent_cells=tuple((int(x), int(y)) for x, y in cells[0]),
        region=batch.region[0],
        usable=batch.usable[0],
        handover=batch.handover[0],
        onion=batch.onion[0],
        plate=batch.plate[0],
        dish=batch.dish[0],
        fillable=batch.fillable[0],
        serves=batch.serves[0],
        delivers=batch.delivers[0],
        solo=batch.solo[0],
        level_class=CLASS_NAMES[int(batch.codes[0])],
    )


def classify_level(grid: np.ndarray, agent_cells) -> str:
    """"solo", "forced_coordination" or "unsolvable" for one level (grid integer (H, W); cells (x, y))."""
    return CLASS_NAMES[int(classify_levels(*_batch_of_one(grid, agent_cells))[0])]


def is_solvable(grid: np.ndarray, agent_cells) -> bool:
    """True when the two agents can deliver a soup (grid integer (H, W); agent_cells ((x, y), (x, y)))."""
    return classify_level(grid, agent_cells) != "unsolvable"


def analyse_layout(layout: Layout) -> LevelReport:
    """`analyse_level` for a `Layout`."""
    return analyse_level(layout.grid, layout.agent_start)


def classify_layout(layout: Layout) -> str:
    """`classify_level` for a `Layout`."""
    return classify_level(layout.grid, layout.agent_start)
