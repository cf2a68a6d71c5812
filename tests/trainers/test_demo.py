"""The kitchen-demo entry point, end to end with a tiny budget."""

import subprocess
import sys
from pathlib import Path

from PIL import Image, ImageSequence

from jax_env.layouts import get_layout
from trainers.demo import main

REPO_ROOT = Path(__file__).resolve().parents[2]


def gif_duration_ms(path):
    with Image.open(path) as gif:
        return sum(frame.info["duration"] for frame in ImageSequence.Iterator(gif))


def test_demo_writes_a_gif_and_reports_the_episode(tmp_path, capsys):
    out = tmp_path / "demo.gif"
    assert main(["--steps", "6", "--seed", "1", "--tile-size", "8", "--out", str(out)]) == 0
    assert gif_duration_ms(out) == 7 * 100  # the start state and one frame per step
    printed = capsys.readouterr().out
    assert "step 6" in printed
    assert "deliveries: 0" in printed
    assert "shaped return:" in printed
    assert str(out) in printed


def test_demo_reads_a_grid_file(tmp_path, capsys):
    grid_file = tmp_path / "tiny.txt"
    grid_file.write_text(get_layout("cramped_room").to_text() + "\n")
    out = tmp_path / "tiny.gif"
    assert main(["--layout", str(grid_file), "--steps", "3", "--tile-size", "8", "--out", str(out)]) == 0
    assert out.exists()
    assert get_layout("cramped_room").to_text().splitlines()[0] in capsys.readouterr().out


def test_unknown_layout_is_a_one_line_error(tmp_path, capsys):
    out = tmp_path / "never.gif"
    assert main(["--layout", "no_such_kitchen", "--out", str(out)]) == 2
    error = capsys.readouterr().err
    assert "no_such_kitchen" in error
    assert len(error.strip().splitlines()) == 1
    assert not out.exists()


def test_malformed_grid_file_is_a_one_line_error(tmp_path, capsys):
    grid_file = tmp_path / "broken.txt"
    grid_file.write_text("WWPWW\nOA AO\nW  W\nWBWXW\n")
    assert main(["--layout", str(grid_file)]) == 2
    error = capsys.readouterr().err
    assert "row 2" in error
    assert len(error.strip().splitlines()) == 1


def test_module_entry_point_exits_with_status_2_without_traceback():
    result = subprocess.run(
        [sys.executable, "-m", "trainers.demo", "--layout", "no_such_kitchen"],
        cwd=REPO_ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 2
    assert "Traceback" not in result.stderr
    assert "no_such_kitchen" in result.stderr
