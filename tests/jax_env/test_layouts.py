import numpy as np
import pytest

from jax_env import (
    CLASSIC_LAYOUTS,
    EXPANDED_LAYOUTS,
    FLOOR,
    GOAL,
    PADDED_LAYOUTS,
    PADDED_LAYOUTS_9X9,
    POT,
    get_layout,
    layout_names,
    parse_layout,
)

VALID = "WWPWW\nOA AO\nW   W\nWBWXW"


def test_parse_valid_grid():
    layout = parse_layout(VALID, name="tiny")
    assert layout.shape == (4, 5)
    assert layout.agent_start == ((1, 1), (3, 1))
    assert layout.grid[0, 2] == POT and layout.grid[3, 3] == GOAL and layout.grid[1, 1] == FLOOR
    assert layout.to_text() == VALID
    assert parse_layout("\n" + VALID + "\n\n").same_map(layout)


@pytest.mark.parametrize(
    "text, message",
    [
        ("WWPWW\nOA AO\nW  W\nWBWXW", "row 2 has 4 cells but row 0 has 5"),
        ("WWPWW\nOA AO\nW Q W\nWBWXW", "unknown symbol 'Q' at row 2, column 2"),
        ("WWPWW\nOA  O\nW   W\nWBWXW", "exactly 2 agents 'A', found 1: (row 1, column 1)"),
        ("WWPWW\nOAAAO\nW   W\nWBWXW", "exactly 2 agents 'A', found 3"),
        ("WWPWW\nOA  O\nA   W\nWBWXW", "an agent on the outer border at row 2, column 0"),
        ("WWPWW\nOA AO\nW    \nWBWXW", "floor on the outer border at row 2, column 4"),
        ("WWPWW\nWA AW\nW   W\nWBWXW", "no onion pile (O)"),
        ("WWPWW\nOA AO\nW   W\nWWWXW", "no plate pile (B)"),
        ("WWWWW\nOA AO\nW   W\nWBWXW", "no pot (P)"),
        ("WWPWW\nOA AO\nW   W\nWBWWW", "no goal (X)"),
        ("", "the grid is empty"),
    ],
)
def test_malformed_grids_are_refused_with_the_place_and_reason(text, message):
    with pytest.raises(ValueError, match="layout 'bad'") as error:
        parse_layout(text, name="bad")
    assert message in str(error.value)


def test_registry_has_every_layout_and_jaxmarl_agent_order():
    padded = set(PADDED_LAYOUTS) | set(PADDED_LAYOUTS_9X9)
    assert set(layout_names()) == set(CLASSIC_LAYOUTS) | set(EXPANDED_LAYOUTS) | padded
    # JaxMARL's agent start cells as flat indices y * W + x.
    expected = {
        "cramped_room": [6, 8],
        "asymm_advantages": [29, 32],
        "coord_ring": [7, 11],
        "forced_coord": [11, 8],
        "counter_circuit": [10, 30],
    }
    for name, flat in expected.items():
        layout = get_layout(name)
        assert [y * layout.width + x for x, y in layout.agent_start] == flat, name
    for name in EXPANDED_LAYOUTS:
        assert get_layout(name).shape == (7, 7)


def test_registered_layouts_match_jaxmarl_cells():
    from jaxmarl.environments.overcooked.layouts import overcooked_layouts

    from jax_env import COUNTER, ONION_PILE, PLATE_PILE

    for name in CLASSIC_LAYOUTS:
        layout, ref = get_layout(name), overcooked_layouts[name]
        flat = layout.grid.reshape(-1)
        assert (layout.height, layout.width) == (ref["height"], ref["width"])
        assert np.array_equal(np.flatnonzero(flat != FLOOR), np.sort(np.asarray(ref["wall_idx"])))
        for kind, key in [
            (GOAL, "goal_idx"),
            (POT, "pot_idx"),
            (ONION_PILE, "onion_pile_idx"),
            (PLATE_PILE, "plate_pile_idx"),
        ]:
            assert np.array_equal(np.flatnonzero(flat == kind), np.sort(np.asarray(ref[key]))), (name, key)
        assert np.any(flat == COUNTER)


def test_unknown_layout_name_lists_the_known_ones():
    with pytest.raises(ValueError, match="unknown layout 'cramped'.*cramped_room_7x7"):
        get_layout("cramped")


def test_start_items_and_numbered_agents_round_trip(tmp_path):
    from jax_env import layout_from_state, load_layout, make_state, save_layout

    text = "WWPWWWW\nO 1   W\nW     d\no   0 W\nWBWXWpW"
    layout = parse_layout(text, name="edited")
    assert layout.agent_start == ((4, 3), (2, 1))
    assert dict(layout.start_items) == {(6, 2): 3, (0, 3): 1, (5, 4): 2}
    assert layout.to_text() == text
    state = make_state(layout)
    assert int(state.contents[2, 6]) == 3 and int(state.contents[3, 0]) == 1
    again = load_layout(save_layout(layout_from_state(state, "edited"), str(tmp_path / "edited.txt")))
    assert again.to_text() == text and again.name == "edited"


def test_numbered_agents_cannot_mix_with_a():
    with pytest.raises(ValueError, match="either with two 'A' or with one '0' and one '1'"):
        parse_layout("WWPWW\nO0 AO\nW   W\nWBWXW", name="bad")
