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
URGENCY_STEPS = 40  # the urgency layer switches on when fewer steps than this remain
_NUM_VALUES = POT_EMPTY + 1  # a cell's value: an item (0..3) or a pot status (0..23)


def _item_channels(features: np.ndarray, item: int) -> None:
    if item == ONION:
        features[23] = 1
    elif item == PLATE:
        features[22] = 1
    elif item == DISH:
        features[18], features[21] = 3, 1


def _cell_table() -> np.ndarray:
    """uint8 (NUM_CELL_KINDS * 24, 26): channels 10-24 of a cell, indexed by kind * 24 + value."""
    table = np.zeros((NUM_CELL_KINDS, _NUM_VALUES, NUM_CHANNELS), dtype=np.uint8)
    for value in range(_NUM_VALUES):
        if value <= DISH:
            _item_channels(table[FLOOR, value], value)  # an agent holding it stands here
            _item_channels(table[COUNTER, value], value)
        table[COUNTER, value, 11] = value == EMPTY  # only empty counters
        table[ONION_PILE, value, 12] = 1
        table[PLATE_PILE, value, 14] = 1
        table[GOAL, value, 15] = 1
        pot = table[POT, value]
        pot[10] = 1
        if value >= POT_FULL:  # filling, not cooking yet
            pot[16] = min(POT_EMPTY - value, 3)
        else:  # cooking or ready
            pot[18], pot[20], pot[21] = 3, value, value == POT_READY
    return table.reshape(NUM_CELL_KINDS * _NUM_VALUES, NUM_CHANNELS)


def _agent_table() -> np.ndarray:
    """uint8 (9, 26): channels 0-9 of a cell; 0 no agent, 1 + d self facing d, 5 + d other facing d."""
    table = np.zeros((9, NUM_CHANNELS), dtype=np.uint8)
    for d in range(4):
        table[1 + d, 0] = table[1 + d, 2 + d] = 1
        table[5 + d, 1] = table[5 + d, 6 + d] = 1
    return table


CELL_TABLE = _cell_table()
AGENT_TABLE = _agent_table()


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
    urgency = jnp.zeros(NUM_CHANNELS, jnp.uint8).at[25].set(urgent.astype(jnp.uint8))
    obs = agents + shared[None] + urgency
    return obs.reshape(2, height, width, NUM_CHANNELS)
