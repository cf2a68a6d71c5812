"""The 26-channel observation (JaxMARL Overcooked v1), built from two per-cell lookup tables.

Channels 10-24 depend only on what a cell is and what it carries, so they are read from one table indexed
by (cell kind, cell value), where a floor cell's value is the item held by the agent standing on it.
Channels 0-9 (who stands where, facing which way) come from a second small table; channel 25 is urgency.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jax_env.layouts import COUNTER, FLOOR, GOAL, NUM_CELL_KINDS, ONION_PILE, PLATE_PILE, POT
from jax_env.state import DISH, EMPTY, ONION, PLATE, POT_EMPTY, POT_FULL, POT_READY, State

NUM_CHANNELS = 26


class Channel:
    """The observation's channels by name (JaxMARL Overcooked v1); agent i's view has its own layers first."""

    SELF, PARTNER = 0, 1  # where the observing agent and its partner stand
    SELF_FACING, PARTNER_FACING = 2, 6  # + direction (NORTH, SOUTH, EAST, WEST): the way each faces
    POT, EMPTY_COUNTER, ONION_PILE, PLATE_PILE, GOAL = 10, 11, 12, 14, 15
    ONIONS_IN_POT = 16  # 0-3 while a pot fills
    COOKING_OR_SOUP = 18  # 3 on a cooking or ready pot, and under a soup anywhere
    COOK_TIME = 20  # a cooking pot's steps left
    SOUP = 21  # a ready pot, or a soup lying or carried
    PLATE, ONION = 22, 23  # an item lying on a counter or held by the agent standing there
    URGENCY = 25  # fewer than URGENCY_STEPS steps left

URGENCY_STEPS = 40  # the urgency layer switches on when fewer steps than this remain
_NUM_VALUES = POT_EMPTY + 1  # a cell's value: an item (0..3) or a pot status (0..23)


def _item_channels(features: np.ndarray, item: int) -> None:
    if item == ONION:
        features[Channel.ONION] = 1
    elif item == PLATE:
        features[Channel.PLATE] = 1
    elif item == DISH:
        features[Channel.COOKING_OR_SOUP], features[Channel.SOUP] = 3, 1


def _cell_table() -> np.ndarray:
    """uint8 (NUM_CELL_KINDS * 24, 26): channels 10-24 of a cell, indexed by kind * 24 + value."""
    table = np.zeros((NUM_CELL_KINDS, _NUM_VALUES, NUM_CHANNELS), dtype=np.uint8)
    for value in range(_NUM_VALUES):
        if value <= DISH:
            _item_channels(table[FLOOR, value], value)  # an agent holding it stands here
            _item_channels(table[COUNTER, value], value)
        table[COUNTER, value, Channel.EMPTY_COUNTER] = value == EMPTY  # only empty counters
        table[ONION_PILE, value, Channel.ONION_PILE] = 1
        table[PLATE_PILE, value, Channel.PLATE_PILE] = 1
        table[GOAL, value, Channel.GOAL] = 1
        pot = table[POT, value]
        pot[Channel.POT] = 1
        if value >= POT_FULL:  # filling, not cooking yet
            pot[Channel.ONIONS_IN_POT] = min(POT_EMPTY - value, 3)
        else:  # cooking or ready
            pot[Channel.COOKING_OR_SOUP], pot[Channel.COOK_TIME], pot[Channel.SOUP] = 3, value, value == POT_READY
    return table.reshape(NUM_CELL_KINDS * _NUM_VALUES, NUM_CHANNELS)


def _agent_table() -> np.ndarray:
    """uint8 (9, 26): channels 0-9 of a cell; 0 no agent, 1 + d self facing d, 5 + d other facing d."""
    table = np.zeros((9, NUM_CHANNELS), dtype=np.uint8)
    for d in range(4):
        table[1 + d, Channel.SELF] = table[1 + d, Channel.SELF_FACING + d] = 1
        table[5 + d, Channel.PARTNER] = table[5 + d, Channel.PARTNER_FACING + d] = 1
    return table


CELL_TABLE = _cell_table()
AGENT_TABLE = _agent_table()


def _cell_views() -> np.ndarray:
    """uint8 (D, 26): every distinct view one cell can give, bar urgency: each (kind, value) row of the cell table,
    and on a floor cell (where agents stand) each with every agent code added; row 0 the empty floor."""
    views = {tuple(np.zeros(NUM_CHANNELS, np.uint8)): None}
    for kind in range(NUM_CELL_KINDS):
        for value in range(_NUM_VALUES):
            row = CELL_TABLE[kind * _NUM_VALUES + value]
            for agent in AGENT_TABLE if kind == FLOOR else AGENT_TABLE[:1]:
                views.setdefault(tuple(row + agent), None)
    return np.array(list(views), dtype=np.uint8)


def _view_hash(views: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """A hash of a cell's view (its channels' dot product with int multipliers, modulo the lookup's size) that tells
    every view of `views` apart, and the lookup from hash to view index: the smallest size and first seed that do."""
    for size in 2 ** np.arange(7, 14):
        for seed in range(64):
            multipliers = np.random.default_rng(seed).integers(1, size, NUM_CHANNELS).astype(np.int32)
            multipliers[Channel.URGENCY] = 0
            keys = (views.astype(np.int64) @ multipliers) % size
            if len(set(keys.tolist())) == len(views):
                lookup = np.zeros(size, np.int32)
                lookup[keys] = np.arange(len(views))
                return multipliers, lookup
    raise AssertionError("no hash tells the cell views apart")


CELL_VIEWS = _cell_views()
_VIEW_MULTIPLIERS, _VIEW_LOOKUP = _view_hash(CELL_VIEWS)


def cell_view_index(obs: jax.Array) -> jax.Array:
    """int32 [..., H, W]: each cell's view among `CELL_VIEWS` (its channels bar urgency), for observations
    [..., H, W, 26] as `get_obs` makes them."""
    keys = jnp.sum(obs.astype(jnp.int32) * jnp.asarray(_VIEW_MULTIPLIERS), -1) % len(_VIEW_LOOKUP)
    return jnp.asarray(_VIEW_LOOKUP)[keys]


def get_obs(state: State, max_steps: int) -> jax.Array:
    """uint8 (2, H, W, 26): agent i's full view at index i (its own layers first)."""
    height, width = state.grid.shape
    cells = jnp.arange(height * width, dtype=jnp.int32)
    kinds = state.grid.reshape(-1).astype(jnp.int32)
    contents = state.contents.reshape(-1).astype(jnp.int32)
    at_agent = cells[None, :] == state.agent_pos[:, None]  # (2, HW)

    held_here = jnp.sum(jnp.where(at_agent, state.agent_inv[:, None], 0), axis=0)
    value = jnp.where(kinds == FLOOR, held_here, contents)
    # Both tables have zeros where the other one writes, so the two lookups add up to the full view.
    shared = jnp.asarray(CELL_TABLE)[kinds * _NUM_VALUES + value]  # (HW, 26)

    self_code = jnp.where(at_agent, 1 + state.agent_dir[:, None], 0)  # (2, HW)
    other_code = jnp.where(at_agent, 5 + state.agent_dir[:, None], 0)[::-1]
    agents = jnp.asarray(AGENT_TABLE)[self_code + other_code]  # (2, HW, 26)

    urgent = (max_steps - state.step) < URGENCY_STEPS
    urgency = jnp.zeros(NUM_CHANNELS, jnp.uint8).at[Channel.URGENCY].set(urgent.astype(jnp.uint8))
    obs = agents + shared[None] + urgency
    return obs.reshape(2, height, width, NUM_CHANNELS)
