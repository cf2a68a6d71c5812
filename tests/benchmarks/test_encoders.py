import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from encoders import overrides, window_means  # noqa: E402


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
