"""The kitchen-levels entry point: printed, exported and drawn levels, the held-out set, hand-made files, errors."""

import subprocess
import sys
from pathlib import Path

import jax
import numpy as np
import pytest
from PIL import Image

from jax_env.generator import HELDOUT_SEED, GeneratorConfig, heldout_grids, sample_levels, sample_training_levels
from jax_env.layouts import load_layout, parse_layout
from jax_env.render import render_contact_sheet
from jax_env.solvability import classify_layout
from jax_env.state import layout_from_state, make_state
from trainers.levels import main

REPO_ROOT = Path(__file__).resolve().parents[2]
# The held-out generator's batch size: every sample here shares its compilation.
N = 100

UNSOLVABLE_TEXT = "OWWPWWW\nW A   W\nW     W\nB     W\nW     W\nW  A  W\nWWWWWXW\n"  # onion pile in a corner


def sampled(seed, n=N):
    """The start states `sample --seed seed --n n` draws, rebuilt from its documented keys."""
    keys = jax.random.split(jax.random.PRNGKey(seed), n)
    return jax.device_get(sample_levels(keys, GeneratorConfig()))


def level_layout(levels, index):
    return layout_from_state(jax.tree_util.tree_map(lambda leaf: leaf[index], levels))


def printed_levels(out):
    """(header, grid text) for each level of `--print` output."""
    blocks = []
    for chunk in out.split("# level ")[1:]:
        header, _, rest = chunk.partition("\n")
        blocks.append((header, rest.split("\n\n")[0]))
    return blocks


def test_sample_prints_levels_that_parse_back_and_are_solvable(capsys):
    assert main(["sample", "--n", str(N), "--seed", "0", "--print"]) == 0
    out = capsys.readouterr().out
    blocks = printed_levels(out)
    assert len(blocks) == N
    levels = sampled(0)
    for index, (header, text) in enumerate(blocks):
        layout = parse_layout(text)
        level_class = classify_layout(layout)
        assert header == f"{index} ({level_class})"
        assert level_class != "unsolvable"
        np.testing.assert_array_equal(layout.grid, levels.grid[index])
    assert f"{N} levels:" in out


def test_export_writes_files_that_rebuild_the_sampled_start_states(tmp_path, capsys):
    out_dir = tmp_path / "levels"
    assert main(["sample", "--n", str(N), "--seed", "1", "--export", str(out_dir)]) == 0
    captured = capsys.readouterr()
    assert str(out_dir) in captured.out
    assert captured.err == ""  # no progress bar for this few files
    files = sorted(out_dir.iterdir())
    assert [f.name for f in files] == [f"level_{i:04d}.txt" for i in range(N)]
    levels = sampled(1)
    for index, path in enumerate(files):
        state = make_state(load_layout(str(path)))
        np.testing.assert_array_equal(state.grid, levels.grid[index])
        np.testing.assert_array_equal(state.contents, levels.contents[index])
        np.testing.assert_array_equal(state.agent_pos, levels.agent_pos[index])


def test_sheet_is_a_png_of_the_labelled_levels(tmp_path, capsys):
    path = tmp_path / "sheets" / "levels.png"
    assert main(["sample", "--n", str(N), "--seed", "2", "--sheet", str(path), "--tile-size", "8"]) == 0
    assert str(path) in capsys.readouterr().out
    with Image.open(path) as png:
        assert png.format == "PNG"
        image = np.asarray(png.convert("RGB"))
    columns = rows = 10
    assert columns * 7 * 8 < image.shape[1] < columns * 7 * 8 + (columns + 1) * 8
    assert rows * 7 * 8 < image.shape[0]
    levels = sampled(2)
    short = {"solo": "solo", "forced_coordination": "forced"}
    labels = [f"{index} {short[classify_layout(level_layout(levels, index))]}" for index in range(N)]
    np.testing.assert_array_equal(image, render_contact_sheet(levels, tile_size=8, labels=labels))


def test_training_sample_never_shows_a_heldout_grid(capsys):
    heldout = {grid.tobytes() for grid in np.asarray(heldout_grids())}
    args = ["sample", "--n", str(N), "--seed", str(HELDOUT_SEED), "--print"]
    # This seed's keys are the ones the held-out levels were drawn from.
    assert main(args) == 0
    plain = [parse_layout(text).grid.tobytes() for _, text in printed_levels(capsys.readouterr().out)]
    assert sum(grid in heldout for grid in plain) > N // 2
    assert main(args + ["--training"]) == 0
    training = [parse_layout(text).grid.tobytes() for _, text in printed_levels(capsys.readouterr().out)]
    assert len(training) == N
    assert not any(grid in heldout for grid in training)


def test_sample_draws_the_kitchens_a_training_config_names(capsys):
    """--kitchen-size, --smaller-kitchens and --intact-walls: the levels training draws with kitchen_size,
    smaller_kitchens and intact_walls, none held out, counted by class."""
    config = GeneratorConfig(size=9, p_smaller=0.5, p_wall_intact=1.0)
    args = ["sample", "--n", str(N), "--training", "--kitchen-size", "9", "--smaller-kitchens", "0.5",
            "--intact-walls", "1", "--print"]
    assert main(args) == 0
    out = capsys.readouterr().out
    keys = jax.random.split(jax.random.PRNGKey(0), N)
    drawn = np.asarray(sample_training_levels(keys, config, heldout_grids(config)).grid)
    printed = np.stack([parse_layout(text).grid for _, text in printed_levels(out)])
    np.testing.assert_array_equal(printed, drawn)
    forced = sum(header.endswith("(forced_coordination)") for header, _ in printed_levels(out))
    assert 10 < forced < 60 and f"{N - forced} solo, {forced} forced_coordination" in out  # 39% of 4,000 draws
    assert main(["heldout", "--kitchen-size", "9"]) == 0
    assert "100 levels:" in capsys.readouterr().out


def test_heldout_export_writes_the_105_heldout_grids(tmp_path, capsys):
    out_dir = tmp_path / "heldout"
    assert main(["heldout", "--export", str(out_dir), "--print"]) == 0
    captured = capsys.readouterr()
    assert "105 levels:" in captured.out
    assert len(printed_levels(captured.out)) == 105
    assert "# level 100 (solo): cramped_room_7x7\n" in captured.out
    assert "writing levels" in captured.err  # the progress bar of a long export
    files = sorted(out_dir.iterdir())
    grids = np.asarray(heldout_grids())
    assert len(files) == len(grids) == 105
    for path, grid in zip(files, grids):
        np.testing.assert_array_equal(load_layout(str(path)).grid, grid)


def test_show_explains_a_hand_made_unsolvable_level(tmp_path, capsys):
    grid_file = tmp_path / "corner_onions.txt"
    grid_file.write_text(UNSOLVABLE_TEXT)
    sheet = tmp_path / "show.png"
    assert main(["show", str(grid_file), "cramped_room", "--sheet", str(sheet)]) == 0
    out = capsys.readouterr().out
    assert UNSOLVABLE_TEXT.strip() in out
    assert "class: unsolvable" in out
    assert "unsolvable: neither agent can reach an onion pile" in out
    assert "class: solo" in out  # cramped_room
    with Image.open(sheet) as png:
        assert png.width > 2 * 7 * 24


def write(tmp_path, name, text):
    path = tmp_path / name
    path.write_text(text)
    return str(path)


@pytest.mark.parametrize(
    "argv, expected",
    [
        (lambda tmp: ["sample", "--n", "0"], "--n must be at least 1"),
        (lambda tmp: ["show", str(tmp / "missing.txt")], "does not exist"),
        (lambda tmp: ["show", "cramped_room", write(tmp, "ragged.txt", "WWPWW\nOA AO\nW  W\nWBWXW\n")], "row 2"),
        (lambda tmp: ["show", write(tmp, "symbol.txt", "WWPWW\nOA AO\nW ? W\nWBWXW\n")], "unknown symbol"),
        (lambda tmp: ["sample", "--sheet", str(tmp / "levels.jpg")], ".png"),
        (lambda tmp: ["sample", "--intact-walls", "1.5"], "--intact-walls must be in [0, 1], got 1.5"),
        (lambda tmp: ["sample", "--smaller-kitchens", "0.5"], "--smaller-kitchens draws smaller kitchens inside"),
    ],
)
def test_errors_are_one_line_with_exit_status_2(tmp_path, capsys, argv, expected):
    assert main(argv(tmp_path)) == 2
    captured = capsys.readouterr()
    assert captured.out == ""
    assert captured.err.startswith("kitchen-levels: error: ")
    assert expected in captured.err
    assert len(captured.err.strip().splitlines()) == 1


def test_module_entry_point_shows_a_layout_and_fails_without_traceback():
    def run(*args):
        return subprocess.run(
            [sys.executable, "-m", "trainers.levels", *args], cwd=REPO_ROOT, capture_output=True, text=True, timeout=120
        )

    shown = run("show", "cramped_room")
    assert shown.returncode == 0
    assert "class: solo" in shown.stdout
    failed = run("show", "no_such_kitchen")
    assert failed.returncode == 2
    assert "Traceback" not in failed.stderr
    assert "no_such_kitchen" in failed.stderr
