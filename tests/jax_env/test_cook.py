"""The scripted cook inside XLA (`jax_env.cook`, which `torch_kitchen.partners.scripted_cook.ScriptedCook` plays
through) plays as the torch cook it replaced did: the same action distributions, to float rounding, for every knob of
a convention, on the classic layouts and generated levels (`data/cook_reference.npz`, that cook's, on the views
`views` makes), one convention or one per row, with its waves or floor tables."""

import hashlib
import random
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch

from jax_env.cook import cook_logits, floor_tables, per_row, walkable_floor
from torch_kitchen.env import KitchenEnv
from torch_kitchen.partners.conventions import Convention, draw_convention
from torch_kitchen.partners.scripted_cook import ScriptedCook, cook_convention

COOK = jax.jit(cook_logits)  # one compilation for every test of a shape
REFERENCE = np.load(Path(__file__).with_name("data") / "cook_reference.npz")

KNOBS = [
    Convention(),
    Convention(name="ewsn", move_order="EWSN"),
    Convention(name="loader", role="loader"),
    Convention(name="server", role="server", preferences={"onion_pickup": 1.0}),
    Convention(name="onions", preferences={"onion_pickup": 0.6, "counter_place": -0.4}),
    Convention(name="idler", preferences={"idle": 1.0}),
    Convention(name="prefer", handover="prefer"),
    Convention(name="avoid", handover="avoid"),
    Convention(name="hot", goal_temperature=1.0),
    Convention(name="moves", move_temperature=0.5),
    Convention(name="noisy", noise=0.1),
]


def _observations(levels, count=16, steps=24, seed=0) -> torch.Tensor:
    """uint8 [count * steps * 2, H, W, 26]: both seats' views along random episodes (cooks meet, carry, cook)."""
    env = KitchenEnv(count, levels=levels, max_steps=256, seed=seed)
    generator = torch.Generator().manual_seed(seed)
    views, tensordict = [], env.reset()
    for _ in range(steps):
        views.append(tensordict["agents", "observation"].clone())
        tensordict["agents", "action"] = torch.randint(0, 6, (count, 2), generator=generator)
        tensordict = env.step(tensordict)["next"]
    return torch.cat(views).flatten(0, 1)


@pytest.fixture(scope="module")
def views():
    """The expanded classic layouts' views, then generated levels' (held-out ones)."""
    return torch.cat([_observations(["cramped_room_7x7", "forced_coord_7x7", "coord_ring_7x7",
                                     "asymm_advantages_7x7", "counter_circuit_7x7"]),
                      _observations("heldout", seed=1)])


def assert_same_distributions(logits, expected: np.ndarray):
    """As distributions, to float rounding: XLA flushes a probability below float32's normal range (e^-100) to 0,
    which torch keeps as a subnormal, so logits that far down differ while the distributions do not."""
    np.testing.assert_allclose(np.asarray(jax.nn.softmax(logits, -1)), expected, rtol=1e-5, atol=1e-7)


def test_the_views_are_those_the_reference_was_taken_on(views):
    assert hashlib.sha256(views.numpy().tobytes()).hexdigest() == str(REFERENCE["views_sha256"])
    assert list(REFERENCE["names"]) == [convention.name for convention in KNOBS]


@pytest.mark.parametrize("index", range(len(KNOBS)), ids=[c.name for c in KNOBS])
def test_the_cook_gives_the_torch_cooks_distributions_for_every_knob(views, index):
    logits = COOK(jnp.asarray(views.numpy()), cook_convention(KNOBS[index]))
    assert_same_distributions(logits, REFERENCE["probs"][index])
    # ScriptedCook, the cook as a torch module, plays through it with the host's floor tables.
    assert_same_distributions(ScriptedCook(KNOBS[index])(views).numpy(), REFERENCE["probs"][index])


def test_one_program_holds_a_convention_per_row(views):
    conventions = [draw_convention(random.Random(seed), f"c{seed}") for seed in range(4)]
    observation = views[-128:]  # generated levels
    rows = [cook_convention(conventions[i % 4]) for i in range(len(observation))]
    stacked = jax.tree_util.tree_map(lambda *leaves: np.stack(leaves), *rows)
    logits = COOK(jnp.asarray(observation.numpy()), per_row(stacked, len(rows)))
    for i, convention in enumerate(conventions):
        seats = jnp.full(len(observation[i::4]), i % 2)  # each row's seat as in the whole batch (a split by seat)
        alone = COOK(jnp.asarray(observation[i::4].numpy()), cook_convention(convention), seats=seats)
        assert_same_distributions(logits[i::4], np.asarray(jax.nn.softmax(alone, -1)))


@pytest.mark.parametrize("convention", [KNOBS[0], KNOBS[6], KNOBS[9]], ids=lambda c: c.name)
def test_floor_tables_and_detours_for_some_rows_give_the_same_plans_as_every_wave(views, convention):
    observation, arrays = jnp.asarray(views.numpy()), cook_convention(convention)
    waves = np.asarray(COOK(observation, arrays))
    tables = jax.jit(floor_tables)(walkable_floor(observation))
    assert tables.shape == (len(views), 49, 49)
    np.testing.assert_array_equal(np.asarray(COOK(observation, arrays, tables)), waves)
    # Tables shared by the kitchens of one floor plan, each row naming its plan; detours for some rows at most.
    plans, plan = np.unique(np.asarray(tables).reshape(len(views), -1), axis=0, return_inverse=True)
    shared = jnp.asarray(plans.reshape(-1, 49, 49))
    for rows in (len(views) // 4, 1):  # enough rows for those beside their partner; too few: every row's waves
        cook = jax.jit(cook_logits, static_argnames="detour_rows")
        np.testing.assert_array_equal(np.asarray(cook(observation, arrays, shared, jnp.asarray(plan.ravel()),
                                                      detour_rows=rows)), waves)
