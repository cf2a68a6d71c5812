import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from PIL import Image  # noqa: E402
from planner_start import main  # noqa: E402
from tiny import TINY  # noqa: E402

from trainers.checkpoint import load_checkpoint  # noqa: E402


def test_both_learners_train_the_same_seeds_and_every_snapshot_is_evaluated(tmp_path, capsys):
    """Tiny runs: the planner-guided learner's first snapshot is the distilled team, then both learners' IPPO
    snapshots every update; each row holds SP, XP between the two seeds and play with the scripted cook."""
    out = tmp_path / "table.md"
    main(["--budget", "128", "--every", "1", "--seeds", "0", "1", "--heldout", "1", "--rollouts", "1",
          "--runs", str(tmp_path / "runs"), "--out", str(out), "--figure", str(tmp_path / "curves.png"), *TINY,
          "distill.rounds=2", "distill.epochs=1"])
    rows = [line.split("|")[1:-1] for line in out.read_text().splitlines() if line.startswith("| ")]
    learners_steps = [(cells[0].strip(), cells[1].strip()) for cells in rows[1:]]
    assert learners_steps == [("scratch", "64"), ("scratch", "128"), ("planner", "0"), ("planner", "64"),
                              ("planner", "128")]
    minutes = {}
    for cells in rows[1:]:
        minutes.setdefault(cells[0].strip(), []).append(float(cells[2]))
        sp, xp, partner = (float(cell) for cell in cells[3:])
        assert sp >= 0 and xp >= 0 and partner >= 0
    assert all(spent == sorted(spent) for spent in minutes.values())  # CPU time only grows along a run
    planner_start = load_checkpoint(tmp_path / "runs" / "planner" / "distilled" / "seed1")
    [ippo] = [run for run in (tmp_path / "runs" / "planner").glob("*/seed1") if run.parent.name != "distilled"]
    assert f"init_from: {tmp_path / 'runs' / 'planner' / 'distilled' / 'seed1'}" in (ippo / "config.yaml").read_text()
    assert planner_start["update"] == 2  # the distilled team: 2 rounds
    assert "| learner | env steps |" in capsys.readouterr().out
    with Image.open(tmp_path / "curves.png") as curves:
        assert curves.width > curves.height > 100
