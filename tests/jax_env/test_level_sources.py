"""The levels an environment plays: generated Infinite Kitchen levels (all solvable, never held out), the
held-out set, lists of layouts, and the batched step with partial resets."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jax_env import (
    EXPANDED_LAYOUTS,
    GeneratorConfig,
    Overcooked,
    classify_levels,
    get_layout,
    heldout_grids,
    sample_training_levels,
)
from jax_env.solvability import CLASS_NAMES


def _training_levels(num_levels, seed):
    keys = jax.random.split(jax.random.PRNGKey(seed), num_levels)
    return sample_training_levels(keys, GeneratorConfig(), heldout_grids())


def _agent_cells(states):
    pos = np.asarray(states.agent_pos)
    return np.stack([pos % 7, pos // 7], axis=-1)


def test_one_hundred_thousand_training_levels_are_all_solvable():
    levels = _training_levels(100_000, seed=1)
    codes = classify_levels(np.asarray(levels.grid), _agent_cells(levels))
    counts = {name: int((codes == i).sum()) for i, name in enumerate(CLASS_NAMES)}
    assert counts["unsolvable"] == 0, counts
    assert counts["solo"] > 0 and counts["forced_coordination"] > 0, counts


def test_no_heldout_level_in_100k_training_draws():
    # The default generator's space is so large that chance alone rarely draws one of its 105 held-out grids: the
    # rejection itself is tested where the held-out set catches a third of plain draws
    # (tests/jax_env/test_generator.py::test_training_never_draws_a_heldout_grid); this guards the default settings.
    heldout = {grid.tobytes() for grid in np.asarray(heldout_grids())}
    assert len(heldout) == 105
    grids = np.asarray(_training_levels(100_000, seed=100).grid)
    assert not any(grid.tobytes() in heldout for grid in grids)


def test_the_checker_rejects_hand_made_unsolvable_levels():
    from jax_env import classify_layout, parse_layout

    walled_pot = parse_layout("WWWWWWW\nO A   W\nW    WW\nW   WPW\nB    WW\nW A   X\nWWWWWWW")
    assert classify_layout(walled_pot) == "unsolvable"


def test_infinite_env_draws_a_new_level_per_episode_and_never_a_heldout_one():
    env = Overcooked("infinite", max_steps=4)
    _, states = env.reset_batch(jax.random.PRNGKey(0), 64)
    first = np.asarray(states.grid)
    step = jax.jit(env.step_batch)
    for t in range(4):
        _, states, _, done, _ = step(jax.random.PRNGKey(t + 1), states, jnp.full((64, 2), 4, jnp.int32))
    assert np.asarray(done).all() and (np.asarray(states.step) == 0).all()
    second = np.asarray(states.grid)
    assert len({g.tobytes() for g in first}) > 50
    assert (first != second).any(axis=(1, 2)).mean() > 0.9
    heldout = {g.tobytes() for g in np.asarray(heldout_grids())}
    assert not any(g.tobytes() in heldout for g in np.concatenate([first, second]))


def test_heldout_env_plays_only_heldout_levels():
    env = Overcooked("heldout", max_steps=10)
    _, states = env.reset_batch(jax.random.PRNGKey(0), 2000)
    heldout = [g.tobytes() for g in np.asarray(heldout_grids())]
    drawn = [heldout.index(g.tobytes()) for g in np.asarray(states.grid)]
    assert len(set(drawn)) > 95  # 2000 draws from 105 levels cover nearly all of them
    for name in EXPANDED_LAYOUTS:
        assert get_layout(name).grid.tobytes() in heldout


def test_a_list_of_layouts_is_sampled_uniformly_per_episode():
    env = Overcooked(["cramped_room_7x7", "forced_coord_7x7"], max_steps=10)
    _, states = env.reset_batch(jax.random.PRNGKey(0), 4000)
    is_forced = (np.asarray(states.grid) == get_layout("forced_coord_7x7").grid).all(axis=(1, 2))
    assert abs(is_forced.mean() - 0.5) < 0.04
    with pytest.raises(ValueError, match="one size"):
        Overcooked(["cramped_room", "cramped_room_7x7"])


def test_step_batch_matches_vmapped_step_and_resets_only_finished_kitchens():
    env = Overcooked("cramped_room_7x7", max_steps=5)
    _, states = env.reset_batch(jax.random.PRNGKey(0), 16)
    states = states.replace(step=jnp.where(jnp.arange(16) < 4, 4, 0).astype(jnp.int32))  # 4 kitchens about to end
    actions = jax.random.randint(jax.random.PRNGKey(1), (16, 2), 0, 6, dtype=jnp.int32)
    obs, new, reward, done, info = env.step_batch(jax.random.PRNGKey(2), states, actions)
    stepped, ref_reward, ref_done, ref_info = jax.vmap(env.step_env)(states, actions)
    np.testing.assert_array_equal(done, np.arange(16) < 4)
    np.testing.assert_array_equal(done, ref_done)
    np.testing.assert_array_equal(reward, ref_reward)
    np.testing.assert_array_equal(info["shaped_reward"], ref_info["shaped_reward"])
    np.testing.assert_array_equal(np.asarray(new.step), np.where(np.arange(16) < 4, 0, 1))
    for leaf_new, leaf_stepped in zip(jax.tree_util.tree_leaves(new), jax.tree_util.tree_leaves(stepped)):
        np.testing.assert_array_equal(np.asarray(leaf_new)[4:], np.asarray(leaf_stepped)[4:])
    np.testing.assert_array_equal(obs, jax.vmap(env.get_obs)(new))


def test_reset_where_resets_exactly_the_masked_kitchens():
    env = Overcooked("infinite", max_steps=50)
    _, states = env.reset_batch(jax.random.PRNGKey(0), 32)
    states = states.replace(step=jnp.full((32,), 7, jnp.int32))
    mask = jnp.arange(32) % 3 == 0
    reset = env.reset_where(jax.random.PRNGKey(5), states, mask)
    np.testing.assert_array_equal(np.asarray(reset.step) == 0, np.asarray(mask))
    changed = (np.asarray(reset.grid) != np.asarray(states.grid)).any(axis=(1, 2))
    assert not changed[~np.asarray(mask)].any() and changed[np.asarray(mask)].mean() > 0.8
    untouched = env.reset_where(jax.random.PRNGKey(5), states, jnp.zeros(32, bool))
    np.testing.assert_array_equal(untouched.grid, states.grid)
