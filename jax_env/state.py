"""The kitchen's state: an immutable pytree of small integer arrays, and a builder for hand-made scenarios."""

from __future__ import annotations

import dataclasses
from typing import Mapping, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from jax_env.layouts import COUNTER, FLOOR, POT, Layout

# What an agent holds or a counter carries (uint8 in `State.contents`, int32 in `State.agent_inv`).
EMPTY, ONION, PLATE, DISH = range(4)
ITEM_NAMES = ("empty", "onion", "plate", "dish")

# Pot status, stored in `State.contents` at pot cells: 23 empty, 22/21/20 one/two/three onions,
# 19..1 cooking (steps left), 0 ready.
POT_EMPTY = 23
POT_FULL = 20
POT_READY = 0

# Directions, equal to the move action that faces them: (dx, dy) per index.
NORTH, SOUTH, EAST, WEST = range(4)
DIR_VECTORS = ((0, -1), (0, 1), (1, 0), (-1, 0))


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class State:
    """One kitchen at one time step. Every field is a jax array; batch by `jax.vmap`.

    grid:      uint8 (H, W)  cell kinds (`jax_env.layouts.FLOOR`, ...); constant within an episode.
    contents:  uint8 (H, W)  the item on each counter (EMPTY/ONION/PLATE/DISH), each pot's status; 0 elsewhere.
    agent_pos: int32 (2,)    flat cell index `y * W + x` of agents 0 and 1.
    agent_dir: int32 (2,)    facing direction (NORTH, SOUTH, EAST, WEST).
    agent_inv: int32 (2,)    held item (EMPTY, ONION, PLATE, DISH).
    step:      int32 ()      steps taken in this episode.
    """

    grid: jax.Array
    contents: jax.Array
    agent_pos: jax.Array
    agent_dir: jax.Array
    agent_inv: jax.Array
    step: jax.Array

    def replace(self, **changes) -> "State":
        return dataclasses.replace(self, **changes)

    def agent_xy(self) -> jax.Array:
        """int32 (..., 2, 2): the agents' (x, y) cells."""
        width = self.grid.shape[-1]
        return jnp.stack([self.agent_pos % width, self.agent_pos // width], axis=-1)


def state_nbytes(state: State) -> int:
    """Bytes of one environment's state (pass an unbatched state)."""
    return int(sum(np.asarray(leaf).nbytes for leaf in jax.tree_util.tree_leaves(state)))


def make_state(
    layout: Layout,
    agent_pos: Sequence[Sequence[int]] | None = None,
    agent_dir: Sequence[int] = (NORTH, NORTH),
    agent_inv: Sequence[int] = (EMPTY, EMPTY),
    pot_status: Mapping[tuple[int, int], int] | None = None,
    counter_items: Mapping[tuple[int, int], int] | None = None,
    step: int = 0,
) -> State:
    """Build a state by hand, for scenarios and tests. Cells are (x, y); unnamed pots are empty.

    agent_pos defaults to the layout's start cells; pot_status maps pot cells to a status in 0..23;
    counter_items maps counter cells to ONION, PLATE or DISH (default: the layout's start items). Raises
    `ValueError` on an impossible state.
    """
    height, width = layout.shape
    grid = np.asarray(layout.grid, dtype=np.uint8)
    contents = np.where(grid == POT, POT_EMPTY, 0).astype(np.uint8)
    agent_pos = layout.agent_start if agent_pos is None else agent_pos
    counter_items = dict(layout.start_items) if counter_items is None else counter_items

    def check_cell(cell, what):
        x, y = (int(c) for c in cell)
        if not (0 <= x < width and 0 <= y < height):
            raise ValueError(f"{what} at (x={x}, y={y}) lies outside the {height}x{width} layout {layout.name!r}")
        return x, y

    positions = [check_cell(p, f"agent {i}") for i, p in enumerate(agent_pos)]
    _check_agents(grid, positions, agent_dir, agent_inv)
    for cell, status in (pot_status or {}).items():
        x, y = check_cell(cell, "pot status")
        if grid[y, x] != POT:
            raise ValueError(f"pot status given at (x={x}, y={y}), which is not a pot")
        if not 0 <= status <= POT_EMPTY:
            raise ValueError(f"pot status {status} at (x={x}, y={y}) is outside 0..23")
        contents[y, x] = status
    for cell, item in counter_items.items():
        x, y = check_cell(cell, "counter item")
        if grid[y, x] != COUNTER:
            raise ValueError(f"item given at (x={x}, y={y}), which is not a plain counter")
        if item not in (ONION, PLATE, DISH):
            raise ValueError(f"counter item {item} at (x={x}, y={y}) is not ONION (1), PLATE (2) or DISH (3)")
        contents[y, x] = item

    return State(
        grid=jnp.asarray(grid),
        contents=jnp.asarray(contents),
        agent_pos=jnp.asarray([y * width + x for x, y in positions], dtype=jnp.int32),
        agent_dir=jnp.asarray(agent_dir, dtype=jnp.int32),
        agent_inv=jnp.asarray(agent_inv, dtype=jnp.int32),
        step=jnp.asarray(step, dtype=jnp.int32),
    )


def _check_agents(grid: np.ndarray, positions: list[tuple[int, int]], agent_dir: Sequence[int],
                  agent_inv: Sequence[int]) -> None:
    """Refuses agents that share a cell or stand off the floor, and directions or inventories out of range."""
    if len(positions) != 2 or positions[0] == positions[1]:
        raise ValueError(f"need two agents on two distinct cells, got {positions}")
    for i, (x, y) in enumerate(positions):
        if grid[y, x] != FLOOR:
            raise ValueError(f"agent {i} at (x={x}, y={y}) is not on a floor cell")
    for i, d in enumerate(agent_dir):
        if d not in range(4):
            raise ValueError(f"agent {i} direction {d} is not one of 0 (N), 1 (S), 2 (E), 3 (W)")
    for i, item in enumerate(agent_inv):
        if item not in range(4):
            raise ValueError(f"agent {i} inventory {item} is not one of 0 (empty), 1 (onion), 2 (plate), 3 (dish)")


def layout_from_state(state: State, name: str = "level") -> Layout:
    """The `Layout` of an unbatched state: its map, the agents' cells and the items on its counters (pots
    and hands are not part of a layout). `make_state(layout_from_state(s))` rebuilds `s` up to facings."""
    grid = np.asarray(state.grid, dtype=np.uint8)
    contents = np.asarray(state.contents)
    width = grid.shape[1]
    agents = tuple((int(p) % width, int(p) // width) for p in np.asarray(state.agent_pos))
    items = tuple(
        ((int(x), int(y)), int(contents[y, x])) for y, x in zip(*np.nonzero((grid == COUNTER) & (contents != EMPTY)))
    )
    return Layout(name=name, grid=grid, agent_start=agents, start_items=items)
