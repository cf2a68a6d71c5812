"""The device benchmarks that `benchmarks/gpu_checks.sh` runs, on tiny shapes on the CPU: they run, and count or
split what they say they do."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from trainers.config import TrainConfig

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

import launches  # noqa: E402
import phases  # noqa: E402

TINY_SHAPE = ["num_envs=4", "rollout_steps=8", "hidden=8", "ppo.minibatches=2", "ppo.epochs=1"]


def test_the_phases_of_every_timed_update_are_labelled_and_leave_the_trainer_as_it_was():
    targets = [(phases.trainers.ppo.loop, "make_collector"), (phases.trainers.ppo.loop, "start_update"),
               (phases.trainers.ppo.loop, "update_teams")]
    originals = {target: getattr(*target) for target in targets}
    totals = phases.phase_seconds("jaxmarl", updates=3, device="cpu", overrides=TINY_SHAPE)
    assert set(totals) == set(phases.PHASES)
    for phase, (wall, busy) in totals.items():
        assert wall > 0 and busy == 0, phase  # a CPU has no device timeline
    assert all(getattr(*target) is function for target, function in originals.items())


def test_gae_launches_fall_from_one_loop_step_per_time_step_to_a_scan_of_log_steps():
    torchrl_loop, scan = launches.audit_advantages(num_envs=2, steps=64)
    assert scan.syncs == torchrl_loop.syncs == 0
    assert torchrl_loop.launches >= 2 * 64 > scan.launches


def test_reference_measures_a_setting_that_chooses_its_own_architecture():
    import train
    from jax_ppo import setting_overrides

    overrides = [*setting_overrides("protocol_gnn"), *TINY_SHAPE, "runtime.teams=2"]
    assert train.throughput("mlp", num_envs=4, rollout_steps=8, updates=2, device="cpu", threads=1,
                            overrides=overrides) > 0


def test_device_busy_time_counts_overlapping_kernels_once_and_annotations_not_at_all():
    def span(id, name, start, end, launcher=0, on_device=False, annotation=False):
        return phases.Span(name, id, launcher, start, end, on_device, annotation)

    collection, update = span(1, "collection", 0, 100), span(2, "update", 100, 200)
    spans = [collection, update, span(3, "aten::mm", 10, 12), span(4, "aten::add", 20, 21),
             span(5, "aten::mm", 150, 152),
             span(0, "gemm", 30, 70, launcher=3, on_device=True), span(0, "add", 50, 90, launcher=4, on_device=True),
             span(0, "collection", 30, 90, launcher=1, on_device=True, annotation=True),  # the range on the device
             span(0, "gemm", 160, 170, launcher=5, on_device=True)]
    busy = phases.busy_seconds(spans, [collection, update])
    assert busy == {"collection": 60 / 1e9, "update": 10 / 1e9}  # 30..90 once, though the kernels overlap


@pytest.mark.slow
def test_the_gpu_checks_dry_run_times_the_default_collector_and_the_main_job_and_records_every_row(tmp_path):
    """`DEVICE=cpu SIZE=tiny benchmarks/gpu_checks.sh`, its headline row, a row that crashes and the main job: the
    script runs as it will on a GPU, and its record holds every row it started, with its status and what it
    measured, the crashed one as failed with the end of its output."""
    root = Path(__file__).resolve().parents[2]
    environment = {**os.environ, "DEVICE": "cpu", "SIZE": "tiny", "RESULTS": str(tmp_path),
                   "ONLY": "protocol_default|crash|main",
                   "EXTRA_ROW": "crash 60 python -c raise(SystemExit('the_row_crashed'))",
                   "PATH": f"{Path(sys.executable).parent}:{os.environ['PATH']}"}
    done = subprocess.run(["bash", "benchmarks/gpu_checks.sh"], cwd=root, env=environment, capture_output=True,
                          text=True, timeout=900)
    assert done.returncode == 0, done.stdout[-2000:] + done.stderr[-2000:]
    (record,) = tmp_path.glob("*.json")
    rows = {row["row"]: row for row in json.loads(record.read_text())["rows"]}
    assert list(rows) == ["protocol_default", "crash", "main"]  # in order, the main job last
    headline = rows["protocol_default"]
    assert headline["collector"] == TrainConfig().runtime.collector  # the default collector, timed first
    assert headline["ours"] > 0 and headline["ratio"] == pytest.approx(headline["ours"] / headline["reference"])
    assert headline["verdict"] in ("PASS", "FAIL") and headline["status"] == "finished"
    assert rows["main"]["status"] == "finished" and rows["main"]["seconds"] > 0
    crashed = rows["crash"]
    assert (crashed["status"], crashed["exit"], crashed["verdict"]) == ("failed", 1, "failed")
    assert "the_row_crashed" in crashed["tail"]
    markdown = record.with_suffix(".md").read_text()
    assert "| protocol_default | finished |" in markdown and "## crash: failed" in markdown
    assert "ours / JAX" in (record.with_suffix("") / "protocol_default.txt").read_text()  # its raw output kept
    assert not (root / "benchmarks" / "results" / "gpu" / record.name).exists()  # the dry run's record stays out
