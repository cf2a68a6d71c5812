"""The solvability checker: classic kitchens, hand-made broken kitchens, and batch/single agreement."""

from collections import deque

import numpy as np
import pytest

from jax_env.layouts import (
    CLASSIC_LAYOUTS,
    COUNTER,
    EXPANDED_LAYOUTS,
    FLOOR,
    GOAL,
    ONION_PILE,
    PLATE_PILE,
    POT,
    get_layout,
    parse_layout,
)
from jax_env.solvability import (
    CLASS_NAMES,
    FORCED_COORDINATION,
    SOLO,
    UNSOLVABLE,
    analyse_layout,
    analyse_level,
    classify_layout,
    classify_level,
    classify_levels,
    is_solvable,
)

FORCED = {"forced_coord", "forced_coord_7x7"}


@pytest.mark.parametrize("name", EXPANDED_LAYOUTS + CLASSIC_LAYOUTS)
def test_registered_layouts_are_solvable(name):
    layout = get_layout(name)
    expected = "forced_coordination" if name in FORCED else "solo"
    assert classify_layout(layout) == expected
    assert is_solvable(layout.grid, layout.agent_start)


def test_forced_coord_explained_by_hand_over():
    report = analyse_layout(get_layout("forced_coord_7x7"))
    assert not report.shared_region
    assert report.handover_counters == ((3, 1), (3, 2), (3, 3), (3, 4), (3, 5))
    assert report.usable_cells(0, ONION_PILE) == ((0, 1), (0, 2)) and report.usable_cells(0, POT) == ()
    assert report.usable_cells(1, POT) == ((6, 1), (6, 2)) and report.usable_cells(1, ONION_PILE) == ()
    assert report.onion.all() and report.plate.all() and report.dish.all()
    assert report.explain().startswith("forced coordination")


def test_cramped_room_7x7_is_solo_for_both():
    report = analyse_layout(get_layout("cramped_room_7x7"))
    assert report.shared_region and report.solo.all()
    assert report.explain().startswith("solo")


# Each level is broken in one way; the reason names it.
BROKEN = {
    "pot walled off": (
        "WWWPWWW\n"
        "OA WWWW\n"
        "W     W\n"
        "W     W\n"
        "W     W\n"
        "W    AW\n"
        "BWWWWXW",
        "no pot can receive onions: neither agent can reach a pot",
    ),
    "plate pile unreachable": (
        "WWWPWWW\n"
        "OA    W\n"
        "W     W\n"
        "W     W\n"
        "W     W\n"
        "WW   AW\n"
        "BWWWWXW",
        "neither agent can reach a plate pile",
    ),
    "goal enclosed": (
        "WWWPWWW\n"
        "OA    W\n"
        "W     W\n"
        "W     W\n"
        "W     W\n"
        "W    AW\n"
        "WBWWWWX",
        "neither agent can reach a goal",
    ),
    "split items, no shared counter": (
        "WWWWWWW\n"
        "OA WW P\n"
        "O  WW P\n"
        "W  WW W\n"
        "B  WW W\n"
        "B  WWAW\n"
        "WWWWWXW",
        "agent 1 reaches pots at (6, 1), (6, 2) but cannot get onions: it uses no onion pile and no hand-over "
        "counter connects it to agent 0",
    ),
    "onions and plates reach different pots": (
        "WWWWWWW\n"
        "OA WW P\n"
        "P  WW W\n"
        "W  WW W\n"
        "W  WW B\n"
        "W  WWAW\n"
        "WWWWWXW",
        "no pot that can receive onions ((0, 2)) can also get a plate",
    ),
    "dish made where no goal is reachable": (
        "WWWWWWW\n"
        "OA WW W\n"
        "O  WW W\n"
        "W  P  W\n"
        "B  WW W\n"
        "W  WWAW\n"
        "WWWWWXW",
        "agent 1 reaches goals at (5, 6) but cannot get a dish: no hand-over counter connects it to agent 0",
    ),
}


@pytest.mark.parametrize("case", list(BROKEN))
def test_broken_levels_are_rejected_with_reason(case):
    text, reason = BROKEN[case]
    layout = parse_layout(text)
    report = analyse_layout(layout)
    assert report.level_class == "unsolvable" and not report.solvable
    assert not is_solvable(layout.grid, layout.agent_start)
    assert reason in report.explain(), report.explain()


def test_removing_the_hand_over_counter_breaks_forced_coord():
    layout = get_layout("forced_coord_7x7")
    grid = layout.grid.copy()
    # A second wall column: the divider's counters no longer touch agent 1's region.
    grid[1:6, 4] = COUNTER
    report = analyse_level(grid, layout.agent_start)
    assert report.level_class == "unsolvable"
    assert report.handover_counters == ()
    assert "no hand-over counter connects it to agent 0" in report.explain()


def test_shared_pot_is_a_meeting_point():
    # Onions on the left, plates and goal on the right; the pot in the divider is the only link.
    layout = parse_layout("WWWWWWW\nOA WW W\nO  WW B\nW  P  W\nW  WW W\nW  WWAW\nWWWWWXW")
    report = analyse_layout(layout)
    assert report.handover_counters == ()
    assert report.level_class == "forced_coordination"
    assert report.dish.tolist() == [False, True]


def test_bad_inputs_raise():
    layout = get_layout("cramped_room_7x7")
    with pytest.raises(ValueError, match="not a floor cell"):
        classify_level(layout.grid, ((0, 0), (1, 1)))
    with pytest.raises(ValueError, match="outside"):
        classify_level(layout.grid, ((9, 1), (1, 1)))
    with pytest.raises(ValueError, match=r"\(N, 2, 2\)"):
        classify_levels(layout.grid[None], np.zeros((1, 2), dtype=np.int64))


# A plain re-statement of the rules as a search over where an item can be (with an agent, or on a
# counter), used to cross-check the vectorised flood fill.
def _reference_class(grid, agents):
    height, width = grid.shape

    def neighbours(x, y):
        for dx, dy in ((1, 0), (-1, 0), (0, 1), (0, -1)):
            if 0 <= x + dx < width and 0 <= y + dy < height:
                yield x + dx, y + dy

    uses = []
    for start in agents:
        seen, queue = {start}, deque([start])
        while queue:
            for nxt in neighbours(*queue.popleft()):
                if grid[nxt[1], nxt[0]] == FLOOR and nxt not in seen:
                    seen.add(nxt)
                    queue.append(nxt)
        uses.append({n for cell in seen for n in neighbours(*cell) if grid[n[1], n[0]] != FLOOR})

    def kind_cells(agent, kind):
        return {c for c in uses[agent] if grid[c[1], c[0]] == kind}

    def holders(first):
        # Agents that can come to hold an item first held by `first`, moving it over counters.
        reached, queue = set(first), deque(first)
        while queue:
            place = queue.popleft()
            if isinstance(place, int):
                nxt = list(kind_cells(place, COUNTER))
            else:
                nxt = [a for a in (0, 1) if place in uses[a]]
            for p in nxt:
                if p not in reached:
                    reached.add(p)
                    queue.append(p)
        return {p for p in reached if isinstance(p, int)}

    onion = holders([a for a in (0, 1) if kind_cells(a, ONION_PILE)])
    plate = holders([a for a in (0, 1) if kind_cells(a, PLATE_PILE)])
    fillable = {p for a in onion for p in kind_cells(a, POT)}
    dish = holders([a for a in plate if kind_cells(a, POT) & fillable])
    if any(all(kind_cells(a, k) for k in (ONION_PILE, PLATE_PILE, POT, GOAL)) for a in (0, 1)):
        return SOLO
    return FORCED_COORDINATION if any(kind_cells(a, GOAL) for a in dish) else UNSOLVABLE


def _random_levels(rng, n, size=7):
    """Random walls inside a counter border, items on random non-floor cells, agents on random floor."""
    grids = np.empty((n, size, size), dtype=np.uint8)
    cells = np.empty((n, 2, 2), dtype=np.int64)
    for i in range(n):
        grid = np.full((size, size), COUNTER, dtype=np.uint8)
        grid[1:-1, 1:-1] = np.where(rng.random((size - 2, size - 2)) < rng.uniform(0.1, 0.5), COUNTER, FLOOR)
        floor = np.argwhere(grid == FLOOR)
        if len(floor) < 2:
            grid[1, 1] = grid[size - 2, size - 2] = FLOOR
            floor = np.argwhere(grid == FLOOR)
        walls = np.argwhere(grid != FLOOR)
        items = [ONION_PILE, PLATE_PILE, POT, GOAL] + list(rng.choice([ONION_PILE, PLATE_PILE, POT, GOAL], 3))
        for (y, x), kind in zip(walls[rng.choice(len(walls), len(items), replace=False)], items):
            grid[y, x] = kind
        start = floor[rng.choice(len(floor), 2, replace=False)]
        grids[i], cells[i] = grid, start[:, ::-1]
    return grids, cells


def test_batched_agrees_with_single_and_reference():
    grids, cells = _random_levels(np.random.default_rng(0), 300)
    codes = classify_levels(grids, cells)
    assert codes.shape == (300,) and codes.dtype == np.int8
    single = [classify_level(g, c) for g, c in zip(grids, cells)]
    assert single == [CLASS_NAMES[c] for c in codes]
    reference = np.array([_reference_class(g, [tuple(map(int, a)) for a in c]) for g, c in zip(grids, cells)])
    np.testing.assert_array_equal(codes, reference)
    # The random mix must exercise every class for the check to mean anything.
    assert set(codes.tolist()) == {UNSOLVABLE, SOLO, FORCED_COORDINATION}
