import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from encoders import main, overrides, window_means  # noqa: E402


def test_window_means_average_each_window_of_steps(tmp_path):
    charts = tmp_path / "csv" / "scalars" / "charts"
    charts.mkdir(parents=True)
    (charts / "episode_deliveries.csv").write_text("100,1.0\n200,3.0\n500,5.0\n600,7.0\n")
    means = window_means(tmp_path, "episode_deliveries", windows=3, budget=600)
    assert means[:1] == [2.0] and math.isnan(means[1]) and means[2] == 6.0


def test_architectures_differ_only_in_architecture_and_run_directory(tmp_path):
    mlp, ego = overrides("mlp", 4096, 0, tmp_path), overrides("ego_mlp", 4096, 0, tmp_path)
    differing = [(a, b) for a, b in zip(mlp, ego) if a != b]
    assert [a.split("=")[0] for a, _ in differing] == ["architecture", "run_dir"]


def test_read_tabulates_finished_runs_without_training(tmp_path, capsys):
    runs = []
    for name, deliveries in (("a", "100,1.0\n600,3.0\n"), ("b", "100,2.0\n600,4.0\n")):
        charts = tmp_path / name / "csv" / "scalars" / "charts"
        charts.mkdir(parents=True)
        (charts / "episode_deliveries.csv").write_text(deliveries)
        (charts / "shaped_return.csv").write_text("100,0.5\n600,0.25\n")
        runs.append(str(tmp_path / name))
    out = tmp_path / "table.md"
    main(["--read", *runs, "--budget", "600", "--windows", "2", "--out", str(out)])
    rows = [line for line in out.read_text().splitlines() if line.startswith(f"| {tmp_path}")]
    assert rows == [f"| {runs[0]} | deliveries | 1.00 | 3.00 |", f"| {runs[0]} | shaped return | 0.50 | 0.25 |",
                    f"| {runs[1]} | deliveries | 2.00 | 4.00 |", f"| {runs[1]} | shaped return | 0.50 | 0.25 |"]
    assert not (tmp_path / "runs").exists() and out.read_text() in capsys.readouterr().out
