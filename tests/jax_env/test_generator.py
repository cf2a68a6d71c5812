"""The Infinite Kitchen generator: structure, frequencies, held-out set, rejection sampling, exact support count."""

import dataclasses
import functools
import importlib.util
import itertools
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jax_env import generator as gen
from jax_env.generator import (
    HELDOUT_SEED,
    GeneratorConfig,
    heldout_grids,
    heldout_levels,
    is_heldout,
    sample_level,
    sample_levels,
    sample_training_level,
)
from jax_env.layouts import COUNTER, EXPANDED_LAYOUTS, FLOOR, GOAL, ONION_PILE, PLATE_PILE, POT, get_layout
from jax_env.state import DISH, ONION, PLATE, POT_EMPTY

ROOT = Path(__file__).resolve().parents[2]
N = 25_000  # levels per sample; every batch in this file has this size so that one compilation serves all
DEFAULT = GeneratorConfig()
NO_EXTRAS = dict(p_extra_item=0.0, p_loose_onion=0.0, p_loose_plate=0.0, p_loose_dish=0.0)
EMPTY_ONLY = dict(p_empty=1.0, p_middle=0.0, p_vertical=0.0, p_horizontal=0.0)


def _load_count_script():
    spec = importlib.util.spec_from_file_location("count_initial_states", ROOT / "scripts" / "count_initial_states.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


count_script = _load_count_script()


def flat(cells) -> np.ndarray:
    return np.asarray([r * 7 + c for r, c in cells])


SAFE = flat(gen.SAFE_CELLS)
QUESTIONABLE = flat(gen.QUESTIONABLE_CELLS)
BORDER = flat(gen.BORDER_CELLS)
QUADRANTS = np.stack([flat(cells) for cells in gen.QUADRANT_CELLS])  # (4, 3)
ITEM_KINDS = (ONION_PILE, PLATE_PILE, POT, GOAL)


@functools.lru_cache(maxsize=None)
def levels(config: GeneratorConfig, seed: int = 0):
    """N levels as numpy arrays (grid and contents flattened to (N, 49))."""
    state = jax.tree_util.tree_map(np.asarray, sample_levels(jax.random.split(jax.random.PRNGKey(seed), N), config))
    return state.replace(grid=state.grid.reshape(N, 49), contents=state.contents.reshape(N, 49))


def assert_frequency(hits, p: float, what: str, z: float = 5.0):
    """The mean of the booleans `hits` is p: exactly when p is 0 or 1, else within z standard errors."""
    hits = np.asarray(hits, dtype=bool)
    mean = hits.mean()
    if p in (0.0, 1.0):
        assert mean == p, f"{what}: frequency {mean}, expected exactly {p}"
    else:
        se = np.sqrt(p * (1 - p) / hits.size)
        assert abs(mean - p) <= z * se, f"{what}: frequency {mean:.4f}, expected {p:.4f} +- {z} x {se:.4f}"


# --- wall classes observable from a grid, and their exact probabilities -----------------------------------


def wall_classes(grid: np.ndarray) -> dict[str, np.ndarray]:
    """bool (N,) per class of interior wall map; the classes partition the levels."""
    interior = grid.reshape(-1, 7, 7)[:, 1:6, 1:6] != FLOOR
    n = interior.sum(axis=(1, 2))
    col, row = interior[:, :, 2], interior[:, 2, :]
    only_col, only_row = n == col.sum(axis=1), n == row.sum(axis=1)
    classes = {
        "empty": n == 0,
        "vertical": only_col & (col[:, 0] | col[:, 4]),
        "horizontal": only_row & (row[:, 0] | row[:, 4]),
        "middle column": only_col & (n == 3) & col[:, 1:4].all(axis=1),
        "middle row": only_row & (n == 3) & row[:, 1:4].all(axis=1),
    }
    classes["block"] = ~np.any(np.stack(list(classes.values())), axis=0)
    return classes


def wall_class_probs(c: GeneratorConfig) -> dict[str, float]:
    """Exact probabilities of the classes: a fully reopened block is empty, and a continuous wall reopened at
    both ends looks like a block keeping only its middle column or row."""
    reopen, kept = c.p_block_reopen, 1 - c.p_block_reopen
    line_shape = kept**3 * reopen**6
    both_ends = (1 - c.p_wall_intact) / 10
    return {
        "empty": c.p_empty + c.p_middle * reopen**9,
        "vertical": c.p_vertical * (1 - both_ends),
        "horizontal": c.p_horizontal * (1 - both_ends),
        "middle column": c.p_middle * line_shape + c.p_vertical * both_ends,
        "middle row": c.p_middle * line_shape + c.p_horizontal * both_ends,
        "block": c.p_middle * (1 - reopen**9 - 2 * line_shape),
    }


# --- structure ----------------------------------------------------------------------------------------------


def check_structure(lv) -> None:
    grid, contents, n = lv.grid, lv.contents, lv.grid.shape[0]
    assert grid.dtype == np.uint8 and contents.dtype == np.uint8
    assert lv.agent_pos.shape == lv.agent_dir.shape == lv.agent_inv.shape == (n, 2) and lv.step.shape == (n,)
    assert lv.agent_pos.dtype == lv.agent_dir.dtype == lv.agent_inv.dtype == lv.step.dtype == np.int32
    assert np.all(grid <= GOAL)
    assert np.all(grid[:, BORDER] != FLOOR), "a border cell is floor"

    # Walls and items off the border only on questionable cells; the classes' walls where the predicates put them.
    off_questionable = np.setdiff1d(np.arange(49), np.union1d(QUESTIONABLE, BORDER))
    assert np.all(grid[:, off_questionable] == FLOOR)
    classes = wall_classes(grid)
    interior = grid.reshape(n, 7, 7)[:, 1:6, 1:6] != FLOOR
    block_class = interior[classes["block"]]
    assert not block_class[:, [0, 4], :].any() and not block_class[:, :, [0, 4]].any()
    assert set(np.unique(interior[classes["vertical"]].sum(axis=(1, 2)))) <= {3, 5}
    assert set(np.unique(interior[classes["horizontal"]].sum(axis=(1, 2)))) <= {3, 5}

    for kind in ITEM_KINDS:
        on_safe = (grid[:, SAFE] == kind).sum(axis=1)
        assert np.all(on_safe == 1), f"kind {kind} is not exactly once on the safe cells"
        assert np.all((grid == kind).sum(axis=1) <= 2), f"more than 2 of kind {kind}"
    is_item = (grid != FLOOR) & (grid != COUNTER)
    not_safe = np.setdiff1d(np.arange(49), SAFE)
    assert np.all(np.isin(np.nonzero(is_item[:, not_safe])[1], np.searchsorted(not_safe, QUESTIONABLE))), (
        "an extra item off the questionable cells"
    )
    assert np.all(grid[:, QUADRANTS.ravel()] == FLOOR), "a quadrant cell is walled"

    quadrant_of = {int(cell): q for q, cells in enumerate(QUADRANTS) for cell in cells}
    q0 = np.array([quadrant_of.get(int(p), -1) for p in lv.agent_pos[:, 0]])
    q1 = np.array([quadrant_of.get(int(p), -1) for p in lv.agent_pos[:, 1]])
    assert np.all(q0 >= 0) and np.all(q1 >= 0), "an agent outside the quadrants"
    assert np.all(q0 + q1 == 3), "agents not in diagonally opposite quadrants"
    assert np.all(np.take_along_axis(grid, lv.agent_pos, axis=1) == FLOOR)
    assert np.all((lv.agent_dir >= 0) & (lv.agent_dir < 4))
    assert np.all(lv.agent_inv == 0) and np.all(lv.step == 0)

    assert np.all(contents[grid == POT] == POT_EMPTY), "a pot that is not empty"
    loose = contents * (grid != POT)
    assert np.all(loose <= DISH)
    assert np.all(grid[loose > 0] == COUNTER), "a loose item off a plain counter"
    for item in (ONION, PLATE, DISH):
        assert np.all((loose == item).sum(axis=1) <= 1)


CONFIGS = {
    "paper": DEFAULT,
    "empty interior": GeneratorConfig(
        **EMPTY_ONLY, p_extra_item=0.2, p_loose_onion=1.0, p_loose_plate=0.3, p_loose_dish=0.0
    ),
    "full block": GeneratorConfig(
        p_empty=0.0, p_middle=1.0, p_vertical=0.0, p_horizontal=0.0, p_block_reopen=0.0, p_extra_item=1.0
    ),
    "intact lines": GeneratorConfig(p_empty=0.0, p_middle=0.0, p_vertical=0.5, p_horizontal=0.5, p_wall_intact=1.0),
    "opened column": GeneratorConfig(p_empty=0.0, p_middle=0.0, p_vertical=1.0, p_horizontal=0.0, p_wall_intact=0.0),
    "skewed": GeneratorConfig(
        p_empty=0.4, p_middle=0.5, p_vertical=0.1, p_horizontal=0.0, p_block_reopen=0.2, p_wall_intact=0.6,
        p_extra_item=0.3, p_loose_onion=0.9, p_loose_plate=0.1, p_loose_dish=0.7,
    ),
}


@pytest.mark.parametrize("name", list(CONFIGS))
def test_structure(name):
    check_structure(levels(CONFIGS[name]))


@pytest.mark.parametrize("name", list(CONFIGS))
def test_frequencies_follow_the_config(name):
    config = CONFIGS[name]
    lv = levels(config)
    classes = wall_classes(lv.grid)
    for cls, p in wall_class_probs(config).items():
        assert_frequency(classes[cls], p, f"wall class {cls}")

    # A continuous wall with a wall at one of its ends stays whole with this conditional probability.
    lines = classes["vertical"] | classes["horizontal"]
    if config.p_vertical + config.p_horizontal > 0:
        p = config.p_wall_intact / (config.p_wall_intact + (1 - config.p_wall_intact) * 0.9)
        walls = (lv.grid[lines].reshape(-1, 7, 7)[:, 1:6, 1:6] != FLOOR).sum(axis=(1, 2))
        assert_frequency(walls == 5, p, "intact wall")
    # Block cells off the cross are walled only by the middle predicate.
    for r, c in ((2, 2), (2, 4), (4, 2), (4, 4)):
        p = config.p_middle * (1 - config.p_block_reopen)
        assert_frequency(lv.grid[:, r * 7 + c] != FLOOR, p, f"block cell {(r, c)}")

    for kind in ITEM_KINDS:
        assert_frequency((lv.grid == kind).sum(axis=1) == 2, config.p_extra_item, f"extra of kind {kind}")
        for cell in SAFE:
            assert_frequency(lv.grid[:, cell] == kind, 1 / 16, f"kind {kind} on safe cell {cell}")
    loose = lv.contents * (lv.grid != POT)
    for item, p in zip((ONION, PLATE, DISH), config.loose_probs):
        assert_frequency((loose == item).any(axis=1), p, f"loose item {item}")

    quadrant = (lv.agent_pos[:, :, None] == QUADRANTS.reshape(1, 1, -1)).argmax(axis=2) // 3  # (N, 2)
    assert_frequency(np.isin(quadrant[:, 0], (0, 3)), 0.5, "quadrant pair (top-left, bottom-right)")
    assert_frequency(np.isin(quadrant[:, 0], (0, 1)), 0.5, "agent 0 in the pair's upper quadrant")
    for agent in (0, 1):
        for cell in QUADRANTS.ravel():
            assert_frequency(lv.agent_pos[:, agent] == cell, 1 / 12, f"agent {agent} on cell {cell}")
        for direction in range(4):
            assert_frequency(lv.agent_dir[:, agent] == direction, 1 / 4, f"agent {agent} facing {direction}")


def test_reopened_pairs_are_uniform():
    lv = levels(CONFIGS["opened column"])
    column = lv.grid.reshape(N, 7, 7)[:, 1:6, 3] == FLOOR
    assert np.all(column.sum(axis=1) == 2)
    for pair in itertools.combinations(range(5), 2):
        assert_frequency(column[:, pair].all(axis=1), 0.1, f"reopened rows {pair}")


def test_config_fields_change_behaviour():
    base = levels(DEFAULT)
    for field in dataclasses.fields(GeneratorConfig):
        if field.name in ("size", "p_empty", "p_middle", "p_vertical", "p_horizontal", "p_smaller"):
            continue  # the predicates sum to 1; p_smaller is 9x9's (its own test)
        changed = levels(dataclasses.replace(DEFAULT, **{field.name: 1.0 - getattr(DEFAULT, field.name) / 2}))
        same = np.array_equal(base.grid, changed.grid) and np.array_equal(base.contents, changed.contents)
        assert not same, f"changing {field.name} changed no level"


def test_config_validation():
    with pytest.raises(ValueError, match="sum to 1"):
        GeneratorConfig(p_empty=0.5)
    with pytest.raises(ValueError, match="p_loose_dish"):
        GeneratorConfig(p_loose_dish=1.5)
    for size in (5, 8, 11):
        with pytest.raises(ValueError, match=f"7x7 or 9x9, not {size}x{size}"):
            GeneratorConfig(size=size)
    config = GeneratorConfig(**EMPTY_ONLY)
    assert hash(config) == hash(GeneratorConfig(p_empty=1, p_middle=0, p_vertical=0, p_horizontal=0))
    assert all(isinstance(getattr(config, f.name), float) for f in dataclasses.fields(config) if f.name != "size")


def test_jit_vmap_and_static_config_agree():
    # The batched sampler traces the config; a static config must give the very same levels.
    config = CONFIGS["skewed"]
    batched = levels(config)
    keys = jax.random.split(jax.random.PRNGKey(0), N)
    static = jax.jit(sample_level, static_argnames="config")
    for i in range(3):
        level = static(keys[i], config=config)
        np.testing.assert_array_equal(np.asarray(level.grid).ravel(), batched.grid[i])
        np.testing.assert_array_equal(np.asarray(level.contents).ravel(), batched.contents[i])
        for field in ("agent_pos", "agent_dir", "agent_inv", "step"):
            np.testing.assert_array_equal(np.asarray(getattr(level, field)), getattr(batched, field)[i])


# --- held-out set and rejection sampling ---------------------------------------------------------------------


def test_heldout_grids():
    grids = np.asarray(heldout_grids())
    assert grids.shape == (105, 7, 7) and grids.dtype == np.uint8
    assert len({g.tobytes() for g in grids}) == 105
    for grid, name in zip(grids[100:], EXPANDED_LAYOUTS):
        np.testing.assert_array_equal(grid, get_layout(name).grid)
    held = heldout_levels()
    np.testing.assert_array_equal(held.grid, grids[:100])
    held_np = jax.tree_util.tree_map(np.asarray, held)
    check_structure(held_np.replace(grid=held_np.grid.reshape(100, 49), contents=held_np.contents.reshape(100, 49)))

    # With HELDOUT_SEED the first 100 keys already give 100 distinct grids, so the set is exactly their levels.
    direct = sample_levels(jax.random.split(jax.random.PRNGKey(HELDOUT_SEED), 100), DEFAULT)
    for a, b in zip(jax.tree_util.tree_leaves(direct), jax.tree_util.tree_leaves(held)):
        np.testing.assert_array_equal(a, b)

    gen._heldout_levels_np.cache_clear()
    np.testing.assert_array_equal(np.asarray(heldout_grids()), grids)
    # One held-out set per size, whatever probabilities training draws with (and so rejects).
    other = GeneratorConfig(p_wall_intact=1.0, p_block_reopen=0.1)
    np.testing.assert_array_equal(np.asarray(heldout_grids(other)), grids)


def test_heldout_skips_repeated_grids(monkeypatch):
    real = gen.sample_levels
    # Every grid of the first batch comes twice: the set must be filled from further keys, deterministically.
    monkeypatch.setattr(gen, "sample_levels", lambda keys, config: real(keys[jnp.arange(keys.shape[0]) // 2], config))
    first = gen._heldout_levels_np.__wrapped__(DEFAULT).grid
    second = gen._heldout_levels_np.__wrapped__(DEFAULT).grid
    assert first.shape == (100, 7, 7) and len({g.tobytes() for g in first}) == 100
    np.testing.assert_array_equal(first, second)
    # The first 50 kept are the 50 distinct grids of the first batch: those of the first 50 keys.
    np.testing.assert_array_equal(first[:50], np.asarray(heldout_grids())[:50])


def test_training_never_draws_a_heldout_grid():
    # Only required items on an empty interior: 43,680 grids, of which the held-out set takes ~19k.
    config = GeneratorConfig(**EMPTY_ONLY, **NO_EXTRAS)
    heldout = np.unique(levels(config, seed=1).grid, axis=0)
    heldout_set = {g.tobytes() for g in heldout}
    assert len(heldout) > 15_000

    plain = levels(config, seed=2).grid
    plain_hits = np.array([g.tobytes() in heldout_set for g in plain])
    assert plain_hits.mean() > 0.3, "the held-out set should catch many plain draws"
    contains = jax.jit(jax.vmap(is_heldout, in_axes=(0, None)))
    hits = contains(jnp.asarray(plain.reshape(N, 7, 7)), jnp.asarray(heldout.reshape(-1, 7, 7)))
    np.testing.assert_array_equal(np.asarray(hits), plain_hits)

    keys = jax.random.split(jax.random.PRNGKey(3), 10_000)
    train = jax.jit(jax.vmap(sample_training_level, in_axes=(0, None, None)))
    drawn = train(keys, config, jnp.asarray(heldout.reshape(-1, 7, 7)))
    grids = np.asarray(drawn.grid).reshape(-1, 49)
    assert not any(g.tobytes() in heldout_set for g in grids)
    assert len({g.tobytes() for g in grids}) > 5_000


def test_training_with_the_real_heldout_set():
    heldout = heldout_grids()
    static = jax.jit(sample_training_level, static_argnums=1)
    contains = jax.jit(is_heldout)
    level = static(jax.random.PRNGKey(0), DEFAULT, heldout)
    assert level.grid.shape == (7, 7) and not bool(contains(level.grid, heldout))
    assert all(bool(contains(heldout[i], heldout)) for i in (0, 17, 99, 100, 104))
    level = static(jax.random.PRNGKey(0), DEFAULT, jnp.zeros((0, 7, 7), jnp.uint8))
    assert level.grid.shape == (7, 7)


# --- the exact support count ---------------------------------------------------------------------------------


def test_count_script_geometry_matches_the_generator():
    assert count_script.SAFE == tuple(sorted(gen.SAFE_CELLS))
    assert count_script.QUESTIONABLE == frozenset(gen.QUESTIONABLE_CELLS)
    assert count_script.BLOCK == gen.BLOCK_CELLS
    assert (count_script.VERTICAL, count_script.HORIZONTAL) == (gen.VERTICAL_CELLS, gen.HORIZONTAL_CELLS)
    fields = dataclasses.asdict(DEFAULT).items()
    seven_by_seven = {key: value for key, value in fields if key not in ("size", "p_smaller")}
    assert count_script.PAPER_PROBS == seven_by_seven
    assert count_script.NUM_AGENT_CELLS == len(gen.QUADRANT_PAIRS) * 3 * 3 * 2


def test_exact_count():
    counts = count_script.count_initial_states()
    assert counts["wall maps"] == 512 + 10 + 10  # the empty map and the two 3-cell lines are also block maps
    assert counts["walls + items"] == 532_180_871_040
    assert counts["+ agents & facings"] == counts["walls + items"] * 576
    assert counts["+ loose items"] == 3_114_628_227_775_733_760
    output = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "count_initial_states.py")], capture_output=True, text=True, check=True
    ).stdout
    assert "3114628227775733760" in output and "4.60e+28" in output


@pytest.mark.parametrize("name", list(count_script.CROSS_CHECKS))
def test_count_matches_sampled_support(name):
    probs = count_script.CROSS_CHECKS[name]
    with_agents = name.startswith("agents")
    sampled, analytic = count_script.cross_check(probs, num_samples=4 * N, batch_size=N, with_agents=with_agents)
    assert analytic <= 2_000
    assert sampled == analytic


# --- 9x9 kitchens --------------------------------------------------------------------------------------------


def test_9x9_training_levels_are_solvable_never_held_out_and_built_as_the_7x7_ones():
    """The same construction in a 9x9 border (`GeneratorConfig(size=9)`): every level solvable, agents in
    diagonally opposite quadrants, required items once each on safe border cells, every predicate drawn, and
    none of its own 100 held-out levels (themselves solvable and distinct) drawn in training."""
    from jax_env.generator import geometry, sample_training_levels
    from jax_env.solvability import UNSOLVABLE, classify_levels

    config = GeneratorConfig(size=9)
    geo = geometry(9)
    heldout = np.asarray(heldout_grids(config))
    assert heldout.shape == (100, 9, 9) and len({grid.tobytes() for grid in heldout}) == 100
    drawn = jax.tree_util.tree_map(np.asarray, sample_training_levels(
        jax.random.split(jax.random.PRNGKey(9), 4_000), config, jnp.asarray(heldout)))
    grids = drawn.grid
    assert grids.shape == (4_000, 9, 9)
    assert not {grid.tobytes() for grid in grids} & {grid.tobytes() for grid in heldout}
    held_out_states = heldout_levels(config)
    for level_grids, positions in ((grids, drawn.agent_pos), (heldout, np.asarray(held_out_states.agent_pos))):
        cells = np.stack([positions % 9, positions // 9], axis=-1)  # (x, y) per agent
        assert (classify_levels(level_grids, cells) != UNSOLVABLE).all()

    flat = grids.reshape(-1, 81)
    assert (flat[:, geo.flat(geo.border)] != FLOOR).all()
    for kind in ITEM_KINDS:
        assert ((flat[:, geo.flat(geo.safe)] == kind).sum(1) == 1).all()
    quadrant_of = {int(cell): q for q, cells in enumerate(geo.quadrants) for cell in geo.flat(cells)}
    quadrants = np.vectorize(lambda cell: quadrant_of.get(int(cell), -1))(drawn.agent_pos)
    assert (quadrants >= 0).all() and (quadrants.sum(1) == 3).all()
    interior = grids[:, 1:8, 1:8] != FLOOR
    full_column = interior[:, :, 3].all(1) & (interior.sum((1, 2)) == 7)
    full_row = interior[:, 3, :].all(1) & (interior.sum((1, 2)) == 7)
    block = interior[:, 2:5, 2:5].sum((1, 2)) == interior.sum((1, 2))
    assert full_column.any() and full_row.any() and (interior.sum((1, 2)) == 0).any() and block.any()


def test_smaller_kitchens_inside_9x9_are_7x7_levels_with_counters_around_and_change_no_full_size_level():
    """`p_smaller`: a share of 9x9 levels is a 7x7 level drawn inside at any offset (the classic layouts' small
    rooms), solvable and never held out; the full-size levels of the same keys and the held-out set are unchanged."""
    from jax_env.generator import geometry, sample_training_levels
    from jax_env.solvability import UNSOLVABLE, classify_levels

    config = GeneratorConfig(size=9, p_smaller=0.5)
    assert (np.asarray(heldout_grids(config)) == np.asarray(heldout_grids(GeneratorConfig(size=9)))).all()
    keys = jax.random.split(jax.random.PRNGKey(5), 2_000)
    drawn = jax.tree_util.tree_map(np.asarray, sample_training_levels(keys, config, heldout_grids(config)))
    full = jax.tree_util.tree_map(np.asarray, sample_levels(keys, GeneratorConfig(size=9)))
    assert not {grid.tobytes() for grid in drawn.grid} & {grid.tobytes() for grid in np.asarray(heldout_grids(config))}
    cells = np.stack([drawn.agent_pos % 9, drawn.agent_pos // 9], axis=-1)
    assert (classify_levels(drawn.grid, cells) != UNSOLVABLE).all()

    inside = drawn.grid[:, 1:8, 1:8].reshape(len(keys), -1)
    smaller = (inside == FLOOR).sum(1) < 25  # a full-size interior has at least 49 - 9 floor cells
    assert 0.45 < smaller.mean() < 0.55
    mixed = jax.tree_util.tree_map(np.asarray, sample_levels(keys, config))  # the same keys, full size or smaller
    kept = (mixed.grid == full.grid).all((1, 2))
    assert 0.45 < kept.mean() < 0.55 and (mixed.agent_pos[kept] == full.agent_pos[kept]).all()
    geo, offsets = geometry(7), set()
    for grid, contents, positions in zip(drawn.grid[smaller], drawn.contents[smaller], drawn.agent_pos[smaller]):
        floor = np.argwhere(grid == FLOOR)  # a 7x7 level's four interior corners are floor (quadrant cells)
        (row, col), (last_row, last_col) = floor.min(0) - 1, floor.max(0) + 1
        assert (last_row - row, last_col - col) == (6, 6)
        offsets.add((row, col))
        window = grid[row : row + 7, col : col + 7].reshape(-1)
        outside = np.ones((9, 9), bool)
        outside[row : row + 7, col : col + 7] = False
        assert (grid[outside] == COUNTER).all() and (contents[outside] == 0).all()
        for kind in ITEM_KINDS:
            assert (window[geo.flat(geo.safe)] == kind).sum() == 1
        assert all(grid[cell // 9, cell % 9] == FLOOR for cell in positions)
    assert offsets == {(r, c) for r in range(3) for c in range(3)}
    with pytest.raises(ValueError, match="7x7 kitchens are the smallest"):
        GeneratorConfig(p_smaller=0.5)
