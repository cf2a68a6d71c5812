"""Rendering: images, GIFs and the text form of hand-built states."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from PIL import Image, ImageSequence

from jax_env.layouts import get_layout
from jax_env.render import AGENT_COLOURS, render_state, state_to_text, write_gif
from jax_env.state import DISH, EAST, EMPTY, NORTH, ONION, PLATE, SOUTH, WEST, make_state

TILE = 16
LAYOUT = get_layout("cramped_room_7x7")  # pots at (3,0) and (6,0); counter at (0,2)
POT = (3, 0)
COUNTER = (0, 2)


def scenario(**overrides):
    settings = dict(agent_pos=[(1, 1), (4, 4)], agent_dir=[EAST, SOUTH])
    settings.update(overrides)
    return make_state(LAYOUT, **settings)


def tile_of(image, cell):
    x, y = cell
    return image[y * TILE : (y + 1) * TILE, x * TILE : (x + 1) * TILE]


def changed_tiles(a, b):
    """The (x, y) cells whose pixels differ between two renders."""
    diff = np.any(a != b, axis=-1).reshape(LAYOUT.height, TILE, LAYOUT.width, TILE).any(axis=(1, 3))
    return {(int(x), int(y)) for y, x in zip(*np.nonzero(diff))}


def colour_mask(image, colour):
    return np.all(image == np.asarray(colour, dtype=np.uint8), axis=-1)


def test_image_shape_and_dtype_for_jax_and_numpy_states():
    state = scenario()
    image = render_state(state, tile_size=TILE)
    assert image.shape == (LAYOUT.height * TILE, LAYOUT.width * TILE, 3)
    assert image.dtype == np.uint8
    as_numpy = jax.tree_util.tree_map(np.asarray, state)
    np.testing.assert_array_equal(render_state(as_numpy, tile_size=TILE), image)


def test_agent_colours_appear_only_on_their_tiles():
    cells = [(1, 1), (4, 4)]
    image = render_state(scenario(agent_pos=cells, agent_inv=[ONION, DISH]), tile_size=TILE)
    for agent, cell in enumerate(cells):
        mask = colour_mask(image, AGENT_COLOURS[agent])
        inside = colour_mask(tile_of(image, cell), AGENT_COLOURS[agent]).sum()
        assert inside > 0
        assert mask.sum() == inside, f"agent {agent}'s colour leaks outside its tile"


def test_turning_changes_only_the_agents_tile():
    facing_east = render_state(scenario(agent_dir=[EAST, SOUTH]), tile_size=TILE)
    for direction in (NORTH, SOUTH, WEST):
        turned = render_state(scenario(agent_dir=[direction, SOUTH]), tile_size=TILE)
        assert changed_tiles(facing_east, turned) == {(1, 1)}


def test_each_pot_phase_has_its_own_look():
    statuses = [23, 22, 21, 20, 12, 1, 0]  # empty, 1-3 onions, cooking, ready
    images = [render_state(scenario(pot_status={POT: s}), tile_size=TILE) for s in statuses]
    for i in range(len(images)):
        for j in range(i + 1, len(images)):
            assert changed_tiles(images[i], images[j]) == {POT}, (statuses[i], statuses[j])


def test_items_on_counters_and_in_hands_are_drawn():
    items = [EMPTY, ONION, PLATE, DISH]
    on_counter = [
        render_state(scenario(counter_items={COUNTER: item} if item else {}), tile_size=TILE) for item in items
    ]
    in_hand = [render_state(scenario(agent_inv=[item, EMPTY]), tile_size=TILE) for item in items]
    for i in range(len(items)):
        for j in range(i + 1, len(items)):
            assert changed_tiles(on_counter[i], on_counter[j]) == {COUNTER}
            assert changed_tiles(in_hand[i], in_hand[j]) == {(1, 1)}


def test_bad_inputs_raise():
    state = scenario()
    with pytest.raises(ValueError, match="tile_size"):
        render_state(state, tile_size=2)
    batched = jax.tree_util.tree_map(lambda leaf: jnp.stack([leaf, leaf]), state)
    with pytest.raises(ValueError, match="unbatched"):
        render_state(batched)


def walking_states():
    """Agent 0 turns through all four directions: every frame differs from the one before."""
    return [scenario(agent_dir=[d, SOUTH], step=t) for t, d in enumerate([NORTH, EAST, SOUTH, WEST, NORTH])]


def gif_frames(path):
    with Image.open(path) as gif:
        return [(frame.size, frame.info["duration"]) for frame in ImageSequence.Iterator(gif)]


def test_gif_from_a_list_and_from_a_time_axis(tmp_path):
    states = walking_states()
    stacked = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *states)
    for name, given in (("list.gif", states), ("stacked.gif", stacked)):
        path = write_gif(given, tmp_path / "clips" / name, tile_size=TILE, fps=10)
        frames = gif_frames(path)
        assert len(frames) == len(states)
        assert all(size == (LAYOUT.width * TILE, LAYOUT.height * TILE) for size, _ in frames)
        assert all(duration == 100 for _, duration in frames)


def test_gif_keeps_the_clip_length_when_frames_repeat(tmp_path):
    still = scenario()
    path = write_gif([still, still, still, scenario(agent_dir=[WEST, SOUTH])], tmp_path / "still.gif", TILE, fps=10)
    frames = gif_frames(path)
    assert len(frames) == 2
    assert sum(duration for _, duration in frames) == 400


def test_text_form_shows_layout_agents_items_and_pots():
    state = scenario(
        agent_dir=[EAST, WEST],
        agent_inv=[ONION, EMPTY],
        pot_status={(3, 0): 21, (6, 0): 12},
        counter_items={(0, 2): ONION, (0, 3): PLATE, (0, 4): DISH},
        step=5,
    )
    text = state_to_text(state)
    rows = text.splitlines()
    assert rows[0] == "WWWPWWP"  # the layout's top row
    assert rows[6] == "BBWWWXX"
    assert rows[1] == "O0    O"
    assert rows[2] == "o     W"
    assert rows[3] == "p     W"
    assert rows[4] == "d   1 W"
    assert "step 5" in text
    assert "agent 0 at (1,1) facing E, holding onion" in text
    assert "agent 1 at (4,4) facing W, holding nothing" in text
    assert "pot (3,0): 2 onions" in text
    assert "pot (6,0): cooking, 12 left" in text
    assert "ready" in state_to_text(scenario(pot_status={POT: 0}))


def test_contact_sheet_lays_levels_out_in_a_grid():
    from jax_env.render import render_contact_sheet

    states = [scenario(agent_dir=[d, SOUTH]) for d in (NORTH, EAST, SOUTH, WEST, NORTH)]
    stacked = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *states)
    sheet = render_contact_sheet(stacked, columns=2, tile_size=TILE)
    assert sheet.dtype == np.uint8 and sheet.ndim == 3 and sheet.shape[2] == 3
    np.testing.assert_array_equal(sheet, render_contact_sheet(states, columns=2, tile_size=TILE))
    level = LAYOUT.height * TILE
    assert 2 * level < sheet.shape[1] <= 2 * level + 3 * TILE  # two columns and their gaps
    assert 3 * level < sheet.shape[0] <= 3 * level + 4 * TILE  # three rows, the last one half full
    first = render_state(states[0], TILE)
    assert any(np.array_equal(sheet[g : g + level, g : g + level], first) for g in range(TILE))

    labelled = render_contact_sheet(states, columns=2, tile_size=TILE, labels=[f"{i} solo" for i in range(5)])
    assert labelled.shape[1] == sheet.shape[1] and labelled.shape[0] > sheet.shape[0]
    mixed = render_contact_sheet([make_state(get_layout("cramped_room")), states[0]], tile_size=TILE)
    assert mixed.shape[1] > 2 * level  # cells take the largest level's size
    with pytest.raises(ValueError, match="labels"):
        render_contact_sheet(states, labels=["too few"])
