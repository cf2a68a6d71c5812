"""Pure-JAX Overcooked: layouts, the stepper, observations and rendering. No torch in here."""

from jax_env.env import DELIVERY_REWARD, INTERACT, NUM_ACTIONS, STAY, Overcooked, ShapingWeights
from jax_env.generator import (
    HELDOUT_SEED,
    GeneratorConfig,
    heldout_grids,
    heldout_levels,
    heldout_set,
    sample_level,
    sample_levels,
    sample_training_level,
    sample_training_levels,
)
from jax_env.layouts import (
    CLASSIC_LAYOUTS,
    COUNTER,
    EXPANDED_LAYOUTS,
    FLOOR,
    GOAL,
    ONION_PILE,
    PADDED_LAYOUTS,
    PADDED_LAYOUTS_9X9,
    PLATE_PILE,
    POT,
    Layout,
    get_layout,
    layout_name,
    layout_names,
    load_layout,
    parse_layout,
    save_layout,
)
from jax_env.observation import Channel, get_obs
from jax_env.solvability import classify_layout, classify_levels, is_solvable
from jax_env.state import (
    DISH,
    EAST,
    EMPTY,
    NORTH,
    ONION,
    PLATE,
    POT_EMPTY,
    POT_FULL,
    POT_READY,
    SOUTH,
    WEST,
    State,
    layout_from_state,
    make_state,
    state_nbytes,
)
