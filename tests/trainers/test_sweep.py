"""kitchen-sweep: a grid through Hydra's local launcher, and a submitit job preempted mid-run that resumes."""

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from trainers.config.compose import compose, group_choices, load_config
from trainers.sweep import as_hydra_overrides, main

ROOT = Path(__file__).resolve().parents[2]
TINY = ["num_envs=2", "rollout_steps=8", "max_steps=8", "hidden=8", "ppo.minibatches=1", "eval_episodes=0", "gif=false",
        "progress=false", "checkpoint_every=1", "init_from=''",  # from scratch, whatever the config starts from
        "runtime.collector=kitchen"]  # a tiny run compiles the XLA rollout for longer than it trains


def kitchen_sweep(cwd: Path, *arguments: str, config: str = "main.yaml") -> subprocess.Popen:
    environment = {**os.environ, "PYTHONPATH": str(ROOT)}
    return subprocess.Popen([sys.executable, "-m", "trainers.sweep", str(ROOT / "configs" / config), *arguments],
                            cwd=cwd, env=environment, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)


def csv_rows(run: Path) -> list[str]:
    path = run / "csv" / "scalars" / "charts" / "collect_seconds.csv"
    return path.read_text().splitlines() if path.exists() else []


def test_a_two_by_two_grid_writes_four_runs_named_by_the_keys_that_vary(tmp_path):
    sweep = kitchen_sweep(tmp_path, "seed=0,1", "ppo.lr=0.001,0.002", "total_steps=32", *TINY, "eval_episodes=1",
                          "eval_heldout=0")
    output, _ = sweep.communicate(timeout=600)
    assert sweep.returncode == 0, output
    assert "kitchen-sweep: the runs are in runs/main/" in output
    runs = sorted(tmp_path.glob("runs/main/*/seed*"))
    assert [str(run.relative_to(tmp_path / "runs" / "main")) for run in runs] == [
        "ppo.lr=0.001/seed0", "ppo.lr=0.001/seed1", "ppo.lr=0.002/seed0", "ppo.lr=0.002/seed1"]
    for run in runs:
        state = torch.load(run / "checkpoints" / "latest.pt", weights_only=False)
        assert state["env_steps"] == 32 and state["config"]["seed"] == int(run.name.removeprefix("seed"))
        assert state["config"]["ppo"]["lr"] == float(run.parent.name.removeprefix("ppo.lr="))
        assert [int(row.split(",")[0]) for row in csv_rows(run)] == [16, 32]
        assert f"| main/{run.parent.name} | cramped_room_7x7 |" in (run / "eval.md").read_text()  # as kitchen-train
    assert list(tmp_path.glob("runs/main/.sweeps/*/multirun.yaml"))  # Hydra's record of the sweep, beside the runs


def test_the_ray_launcher_runs_a_grid_on_a_local_ray_cluster(tmp_path):
    # The launcher of a multi-GPU box without SLURM; it comes with the ray extra (`pip install -e .[ray]`).
    pytest.importorskip("hydra_plugins.hydra_ray_launcher", reason="the Ray launcher is in the ray extra")
    sweep = kitchen_sweep(tmp_path, "seed=0,1", "total_steps=32", *TINY, "hydra/launcher=ray",
                          "+hydra.launcher.ray.init.num_cpus=2", "+hydra.launcher.ray.init.include_dashboard=false")
    output, _ = sweep.communicate(timeout=600)
    assert sweep.returncode == 0, output
    for seed in (0, 1):
        state = torch.load(tmp_path / "runs" / "main" / f"seed{seed}" / "checkpoints" / "latest.pt", weights_only=False)
        assert (state["env_steps"], state["config"]["seed"]) == (32, seed)


@pytest.mark.parametrize("algorithm, architecture", [("ippo", "mlp"), ("ippo", "gnn_lstm"), ("e3t", "e3t_gnn")])
def test_the_regimes_are_those_of_the_shipped_configs(algorithm, architecture):
    for regime in group_choices("regime"):
        values = compose(None, [f"regime={regime}"])  # what the group sets, as a sweep's point composes it
        shipped = load_config(ROOT / "configs" / algorithm / f"{architecture.removeprefix('e3t_')}_{regime}.yaml")
        assert {key: getattr(shipped, key) for key in values} == values, regime


def test_a_grid_of_regimes_trains_the_shipped_configs_under_their_own_names(tmp_path):
    # The paper's grid in one sweep: each run is the shipped config of its regime and architecture, as its name says.
    sweep = kitchen_sweep(tmp_path, "regime=ik,sk_coord_ring", "architecture=gnn", "seed=0", "total_steps=16",
                          "name=ippo_${architecture}_${hydra:runtime.choices.regime}", *TINY,
                          config="ippo/mlp_ik.yaml")
    output, _ = sweep.communicate(timeout=600)
    assert sweep.returncode == 0, output
    for condition in ("gnn_ik", "gnn_sk_coord_ring"):
        run = tmp_path / "runs" / f"ippo_{condition}" / "seed0"
        trained = load_config(run / "config.yaml")
        shipped = load_config(ROOT / "configs" / "ippo" / f"{condition}.yaml", ["total_steps=16", *TINY])
        assert trained == shipped, condition


def test_keys_and_values_are_checked_before_any_job_starts(tmp_path, capsys, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert main([str(ROOT / "configs" / "main.yaml"), "lrr=0.1,0.2"]) == 2
    refused = capsys.readouterr().err
    assert "unknown config key 'lrr' in the command line (did you mean 'ppo.lr'?); valid keys: name, " in refused
    assert main([str(ROOT / "configs" / "main.yaml"), "seed=0,x"]) == 2
    assert "seed in the command line must be int, got 'x'" in capsys.readouterr().err
    assert main([str(ROOT / "configs" / "main.yaml"), "num_envs=2,3", "ppo.minibatches=2"]) == 2
    assert "minibatches (2) must divide num_envs (3)" in capsys.readouterr().err
    assert main([str(ROOT / "configs" / "main.yaml"), "regime=ik,sk_nowhere"]) == 2
    assert ("regime on the command line must be one of ik, sk_asymm_advantages, sk_coord_ring, sk_counter_circuit, "
            "sk_cramped_room, sk_forced_coord, got 'sk_nowhere'") in capsys.readouterr().err
    assert not (tmp_path / "runs").exists()


def submitit_task(folder: Path) -> int | None:
    """The process id of the submitit task running under `folder`, if one is running."""
    for cmdline in Path("/proc").glob("[0-9]*/cmdline"):
        try:
            command = cmdline.read_bytes().split(b"\0")
        except OSError:
            continue
        if b"submitit.core._submit" in command and any(str(folder).encode() in part for part in command):
            return int(cmdline.parent.name)
    return None


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="finds the submitit task through /proc")
@pytest.mark.slow
def test_a_preempted_submitit_job_is_requeued_and_resumes_from_its_checkpoint(tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher", reason="needs hydra-submitit-launcher (sweep extra)")
    sweep = kitchen_sweep(tmp_path, "seed=0", "total_steps=800", "hydra/launcher=submitit_local", *TINY)
    run = tmp_path / "runs" / "main" / "seed0"
    deadline = time.monotonic() + 300
    checkpoint = run / "checkpoints" / "latest.pt"
    while time.monotonic() < deadline and not (len(csv_rows(run)) >= 20 and checkpoint.exists()):
        assert sweep.poll() is None, sweep.communicate()[0]
        time.sleep(0.2)
    task = submitit_task(tmp_path / "runs")
    assert task is not None
    logged = csv_rows(run)
    os.kill(task, signal.SIGUSR2)  # what SLURM sends before preempting or timing out a job
    output, _ = sweep.communicate(timeout=600)
    assert sweep.returncode == 0, output
    submitit_log = "".join(path.read_text() for path in tmp_path.glob("runs/main/.sweeps/*/.submitit/*/*.out"))
    assert "Requeued job" in submitit_log and submitit_log.count("Loading pickle") == 2
    final = csv_rows(run)
    assert [int(row.split(",")[0]) for row in final] == list(range(16, 801, 16))  # every update once
    # The rows before the preemption are the very ones logged then (timings): resumed, not trained again.
    assert final[: len(logged) - 1] == logged[:-1]
    assert torch.load(checkpoint, weights_only=False)["env_steps"] == 800


def test_groups_sweep_as_groups_and_keys_as_values_whether_or_not_the_file_names_them(tmp_path):
    (tmp_path / "mine.yaml").write_text("hidden: 32\n")
    grid = {"regime": ["ik", "sk_coord_ring"], "architecture": ["mlp", "my_plugin_net"], "seed": ["0", "1"]}
    assert as_hydra_overrides(str(ROOT / "configs" / "main.yaml"), grid) == [
        "regime=ik,sk_coord_ring", "++architecture=mlp,my_plugin_net", "++seed=0,1"]
    assert as_hydra_overrides(str(tmp_path / "mine.yaml"), grid)[0] == "+regime=ik,sk_coord_ring"
