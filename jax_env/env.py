"""The Overcooked stepper: pure functions over `State`, matching JaxMARL's Overcooked (v1) step for step."""

from __future__ import annotations

import copy
import functools
from typing import NamedTuple, Sequence, Union

import jax
import jax.numpy as jnp

from jax_env.generator import GeneratorConfig, heldout_grids, heldout_set, sample_training_level
from jax_env.layouts import (
    COUNTER,
    FLOOR,
    GOAL,
    ONION_PILE,
    PLATE_PILE,
    POT,
    Layout,
    load_layout,
)
from jax_env.observation import get_obs
from jax_env.state import (
    DIR_VECTORS,
    DISH,
    EMPTY,
    ONION,
    PLATE,
    POT_EMPTY,
    POT_FULL,
    POT_READY,
    State,
    make_state,
)

STAY, INTERACT = 4, 5  # actions 0-3 move (and face) north, south, east, west
NUM_ACTIONS = 6
DELIVERY_REWARD = 20.0


class ShapingWeights(NamedTuple):
    """Per-agent shaped rewards (JaxMARL's defaults); reported in `info["shaped_reward"]`, never in `reward`."""

    onion_in_pot: float = 3.0
    plate_pickup: float = 3.0  # only when useful: no plate on a counter, fewer plates held than busy pots
    soup_pickup: float = 5.0


Levels = Union[str, Layout, Sequence[Union[str, Layout]]]


def compiled_when_eager(*static_argnums: int):
    """A method of `Overcooked` compiled by `jax.jit` where it is called on concrete arrays (the env and the
    `static_argnums` static), as JaxMARL's reset and step are: op by op, a batch reset of the Infinite Kitchen's
    generator compiles each of its hundreds of operations alone. Called while JAX traces (under `jit`, `vmap`, or
    over traced start states), it runs as written, into the caller's program."""

    def decorate(method):
        compiled = jax.jit(method, static_argnums=(0, *static_argnums))

        @functools.wraps(method)
        def call(self, *args, **kwargs):
            leaves = jax.tree_util.tree_leaves((self._bank, args, kwargs))
            traced = any(isinstance(leaf, jax.core.Tracer) for leaf in leaves)
            return (method if traced else compiled)(self, *args, **kwargs)

        return call

    return decorate


class Overcooked:
    """A two-agent Overcooked kitchen with JaxMARL's API.

        env = Overcooked("cramped_room", max_steps=400)
        obs, state = env.reset(key)                                   # obs uint8 (2, H, W, 26)
        obs, state, reward, done, info = env.step(key, state, actions)  # actions int32 (2,)

    `levels` chooses the kitchen of every episode (at reset and at every auto-reset):
      - a layout name, a text-grid file or a `Layout`: that kitchen, with random start facings (as JaxMARL);
      - a list of them (all of one size): one drawn uniformly per episode;
      - "infinite": a fresh Infinite Kitchen level per episode from `generator`, held-out levels rejected;
      - "heldout": one of the 105 held-out evaluation levels per episode (100 generated + 5 expanded classics).

    `step` resets a finished episode in the same call (done=True comes with the new episode's observation),
    so `jax.vmap(env.step)` runs thousands of kitchens with no Python in the loop. Every method is pure and
    jittable; the levels and settings are static. Called on concrete arrays, reset and step (and their batched
    forms) are compiled whole, as JaxMARL's are (`compiled_when_eager`); under `jit` or `vmap` they trace as written.
    """

    def __init__(
        self,
        levels: Levels = "cramped_room",
        max_steps: int = 400,
        shaping: ShapingWeights = ShapingWeights(),
        generator: GeneratorConfig = GeneratorConfig(),
    ):
        if max_steps < 1:
            raise ValueError(f"max_steps must be positive, got {max_steps}")
        self.max_steps = int(max_steps)
        self.shaping = ShapingWeights(*shaping)
        self.generator = generator
        self.levels = levels if isinstance(levels, str) else getattr(levels, "name", "custom")
        self.layout: Layout | None = None  # the kitchen, when there is exactly one
        self._bank: State | None = None  # start states to draw from, batched (N, ...)
        self._heldout_grids = None
        if isinstance(levels, str) and levels == "infinite":
            self._heldout_grids = heldout_grids(generator)
            height, width = self._heldout_grids.shape[1:]
        else:
            if isinstance(levels, str) and levels == "heldout":
                self._bank = heldout_set(generator)
            else:
                layouts = [levels] if isinstance(levels, (str, Layout)) else list(levels)
                if not layouts:
                    raise ValueError("levels is an empty list; give at least one layout")
                layouts = [load_layout(x) if isinstance(x, str) else x for x in layouts]
                shapes = {layout.shape for layout in layouts}
                if len(shapes) > 1:
                    raise ValueError(f"all layouts of one environment must have one size, got {sorted(shapes)}")
                self.layout = layouts[0] if len(layouts) == 1 else None
                starts = [make_state(layout) for layout in layouts]
                self._bank = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *starts)
            height, width = self._bank.grid.shape[1:]
        self.height, self.width = int(height), int(width)
        self.obs_shape = (self.height, self.width, 26)
        self.num_actions = NUM_ACTIONS
        # A direction as a step in flat cell indices.
        self._dir_offsets = jnp.asarray([dx + dy * self.width for dx, dy in DIR_VECTORS], dtype=jnp.int32)

    def __repr__(self) -> str:
        return f"Overcooked(levels={self.levels!r}, {self.height}x{self.width}, max_steps={self.max_steps})"

    # ----------------------------------------------------------------------------------------------------
    # Reset
    @compiled_when_eager()
    def initial_state(self, key: jax.Array, level: jax.Array | None = None) -> State:
        """A fresh episode: the level's start cells (or a new generated level), uniformly random facings.

        `level` (int32 ()): the index of the level to play in the list of levels (`num_levels`); None draws one.
        """
        if self._heldout_grids is not None:
            if level is not None:
                raise ValueError("the Infinite Kitchen generates its levels: it has no level to pin an episode to")
            return sample_training_level(key, self.generator, self._heldout_grids)
        # Same key derivation as JaxMARL's reset (its first split draws random start cells, ours the level),
        # so with one layout equal keys give equal facings.
        key, key_level = jax.random.split(key)
        _, key_dir = jax.random.split(key)
        if level is None:
            level = jax.random.randint(key_level, (), 0, self.num_levels)
        start = jax.tree_util.tree_map(lambda leaf: leaf[level], self._bank)
        facing = jax.random.randint(key_dir, (2,), 0, 4, dtype=jnp.int32)
        return start.replace(agent_dir=facing)

    @property
    def num_levels(self) -> int:
        """How many levels episodes are drawn from (0 for the Infinite Kitchen, which generates them)."""
        return 0 if self._bank is None else int(self._bank.step.shape[0])

    @property
    def start_states(self) -> State | None:
        """The start state of every level episodes are drawn from, batched (None for the Infinite Kitchen)."""
        return self._bank

    @property
    def settings(self) -> tuple:
        """Everything the methods depend on but the levels' start states: kitchens with equal settings step alike,
        so one compiled program serves them all, given each one's `start_states` (see `with_start_states`)."""
        generated = self._heldout_grids is not None
        return (self.height, self.width, self.max_steps, self.shaping, self.generator, generated, self.num_levels)

    def with_start_states(self, start_states: State | None) -> "Overcooked":
        """These settings over other levels of the same size and number (traced arrays too): inside a jitted
        function that takes the start states as an argument, kitchens that differ only in their levels share it."""
        other = copy.copy(self)
        other._bank = start_states
        return other

    @compiled_when_eager()
    def reset(self, key: jax.Array) -> tuple[jax.Array, State]:
        state = self.initial_state(key)
        return self.get_obs(state), state

    @compiled_when_eager()
    def get_obs(self, state: State) -> jax.Array:
        """uint8 (2, H, W, 26), see `jax_env.observation`."""
        return get_obs(state, self.max_steps)

    # ----------------------------------------------------------------------------------------------------
    # Step
    @compiled_when_eager()
    def step(self, key: jax.Array, state: State, actions: jax.Array):
        """One step with auto-reset: (obs, state, reward float32 (2,), done bool (), info).

        info["shaped_reward"] is float32 (2,). On the terminal step the returned obs and state are the new
        episode's, the reward the terminal step's.
        """
        _, key_reset = jax.random.split(key)
        next_state, reward, done, info = self.step_env(state, actions)
        fresh = self.initial_state(key_reset)
        next_state = jax.tree_util.tree_map(lambda new, old: jnp.where(done, new, old), fresh, next_state)
        # The observation is built once, from the state that is returned.
        return self.get_obs(next_state), next_state, reward, done, info

    # ----------------------------------------------------------------------------------------------------
    # Batches
    @compiled_when_eager(2)
    def reset_batch(self, key: jax.Array, num_envs: int, levels: jax.Array | None = None) -> tuple[jax.Array, State]:
        """`num_envs` fresh episodes: obs uint8 (B, 2, H, W, 26) and a State with leading axis B.

        `levels` (int32 (B,)): kitchen b plays level levels[b] of the list; None draws a level per kitchen."""
        states = self._fresh(key, num_envs, levels)
        return jax.vmap(self.get_obs)(states), states

    @compiled_when_eager()
    def reset_where(self, key: jax.Array, states: State, mask: jax.Array, levels: jax.Array | None = None) -> State:
        """Batched states with the kitchens where `mask` (bool (B,)) is set replaced by fresh episodes.

        New levels are drawn only when some kitchen needs one: generating an Infinite Kitchen level costs
        several steps, and batched episodes usually end together. `levels` as in `reset_batch`."""

        def with_fresh(states):
            fresh = self._fresh(key, mask.shape[0], levels)
            def pick(new, old):
                return jnp.where(mask.reshape(mask.shape + (1,) * (old.ndim - 1)), new, old)

            return jax.tree_util.tree_map(pick, fresh, states)

        return jax.lax.cond(jnp.any(mask), with_fresh, lambda states: states, states)

    def _fresh(self, key: jax.Array, num_envs: int, levels: jax.Array | None) -> State:
        keys = jax.random.split(key, num_envs)
        if levels is None:
            return jax.vmap(self.initial_state)(keys)
        return jax.vmap(self.initial_state)(keys, levels)

    @compiled_when_eager()
    def step_batch(self, key: jax.Array, states: State, actions: jax.Array):
        """`step` for a batch (leaves with leading axis B, actions int32 (B, 2)), auto-resetting the finished
        kitchens: (obs (B, 2, H, W, 26), states, reward (B, 2), done (B,), info). Same dynamics as
        `jax.vmap(step)`; reset levels come from `key` and are only generated on steps where one is needed."""
        next_states, reward, done, info = jax.vmap(self.step_env)(states, actions)
        next_states = self.reset_where(key, next_states, done)
        return jax.vmap(self.get_obs)(next_states), next_states, reward, done, info

    @compiled_when_eager()
    def step_env(self, state: State, actions: jax.Array):
        """One step without reset or observation: (state, reward (2,), done (), info)."""
        actions = jnp.asarray(actions, dtype=jnp.int32)
        kinds = state.grid.reshape(-1)
        contents = state.contents.reshape(-1)
        pos = state.agent_pos

        # Movement: a move into anything but floor is refused; meeting or swapping agents both stay.
        is_move = actions < STAY
        target = pos + self._dir_offsets[jnp.minimum(actions, 3)]
        target = jnp.where(is_move & (kinds[target] == FLOOR), target, pos)
        collide = target[0] == target[1]
        swap = (target[0] == pos[1]) & (target[1] == pos[0])
        new_pos = jnp.where(collide | swap, pos, target)
        new_dir = jnp.where(is_move, actions, state.agent_dir)

        # Interactions use the cells faced before this step; agent 1 acts on the world agent 0 left.
        facing = pos + self._dir_offsets[state.agent_dir]
        inventory = state.agent_inv
        delivered, shaped = [], []
        for agent in range(2):
            contents, inventory, agent_delivered, agent_shaped = self._interact(
                kinds, contents, inventory, agent, facing[agent], actions[agent] == INTERACT
            )
            delivered.append(agent_delivered)
            shaped.append(agent_shaped)

        # Pots with three onions count down to ready.
        cooking = (kinds == POT) & (contents >= 1) & (contents <= POT_FULL)
        contents = jnp.where(cooking, contents - 1, contents).astype(jnp.uint8)

        step = state.step + 1
        next_state = state.replace(
            contents=contents.reshape(state.contents.shape),
            agent_pos=new_pos,
            agent_dir=new_dir,
            agent_inv=inventory,
            step=step,
        )
        sparse = DELIVERY_REWARD * (delivered[0].astype(jnp.float32) + delivered[1].astype(jnp.float32))
        reward = jnp.stack([sparse, sparse])
        done = step >= self.max_steps
        return next_state, reward, done, {"shaped_reward": jnp.stack(shaped).astype(jnp.float32)}

    def _interact(self, kinds, contents, inventory, agent, cell, acting):
        """Agent `agent` interacts with flat cell `cell` if `acting`: (contents, inventory, delivered, shaped)."""
        kind = kinds[cell]
        value = contents[cell].astype(jnp.int32)
        held = inventory[agent]
        hands_free = held == EMPTY

        take_onion = acting & (kind == ONION_PILE) & hands_free
        take_plate = acting & (kind == PLATE_PILE) & hands_free
        pick_up = acting & (kind == COUNTER) & (value != EMPTY) & hands_free
        put_down = acting & (kind == COUNTER) & (value == EMPTY) & ~hands_free
        add_onion = acting & (kind == POT) & (value > POT_FULL) & (held == ONION)
        take_soup = acting & (kind == POT) & (value == POT_READY) & (held == PLATE)
        deliver = acting & (kind == GOAL) & (held == DISH)

        new_held = jnp.select(
            [take_onion, take_plate, pick_up, take_soup, put_down | add_onion | deliver],
            [ONION, PLATE, value, DISH, EMPTY],
            held,
        )
        new_value = jnp.select(
            [pick_up, put_down, add_onion, take_soup], [EMPTY, held, value - 1, POT_EMPTY], value
        )

        # A plate pays only when nothing suggests it is surplus, judged before this interaction.
        plate_on_counter = jnp.any((kinds == COUNTER) & (contents == PLATE))
        busy_pots = jnp.sum((kinds == POT) & (contents != POT_EMPTY))
        plates_held = jnp.sum(inventory == PLATE)
        got_plate = take_plate | (pick_up & (value == PLATE))
        useful_plate = got_plate & ~plate_on_counter & (plates_held < busy_pots)

        shaped = (
            self.shaping.onion_in_pot * add_onion
            + self.shaping.soup_pickup * take_soup
            + self.shaping.plate_pickup * useful_plate
        )
        contents = contents.at[cell].set(new_value.astype(contents.dtype))
        inventory = inventory.at[agent].set(new_held)
        return contents, inventory, deliver, shaped
