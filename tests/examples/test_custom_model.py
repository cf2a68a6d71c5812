"""examples/train_custom_model.py, end to end with a tiny budget."""

import contextlib
import importlib.util
import io
import math
from pathlib import Path

import pytest
import torch
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensordict import TensorDict

from torch_kitchen.env import KitchenEnv

SCRIPT = Path(__file__).resolve().parents[2] / "examples" / "train_custom_model.py"
# Loaded by path: examples/ is a folder of scripts, not a package.
_spec = importlib.util.spec_from_file_location("train_custom_model", SCRIPT)
train_custom_model = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(train_custom_model)

TAGS = ["charts/episode_deliveries", "charts/steps_per_second", "losses/objective", "losses/critic", "losses/entropy"]


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    """Two iterations of 4 kitchens x 16 steps (one full episode per kitchen per iteration)."""
    log_dir = tmp_path_factory.mktemp("runs")
    argv = ["--envs", "4", "--rollout-steps", "16", "--max-steps", "16", "--total-steps", "128",
            "--epochs", "2", "--minibatches", "2", "--log-dir", str(log_dir), "--seed", "1"]
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        result = train_custom_model.main(argv)
    return result, log_dir, printed.getvalue()


def test_prints_one_line_per_iteration(run):
    result, _, printed = run
    lines = printed.strip().splitlines()
    assert [line.split()[:2] for line in lines] == [["iter", "1/2"], ["iter", "2/2"]]
    assert result["steps"] == 128


def test_writes_finite_namespaced_scalars_to_tensorboard(run):
    result, log_dir, _ = run
    assert Path(result["log_dir"]).parent == log_dir
    assert list(Path(result["log_dir"]).glob("events.out.tfevents.*"))
    events = EventAccumulator(result["log_dir"])
    events.Reload()
    assert set(TAGS) <= set(events.Tags()["scalars"])
    for tag in TAGS:
        scalars = events.Scalars(tag)
        assert [s.step for s in scalars] == [64, 128], tag
        assert all(math.isfinite(s.value) for s in scalars), tag


def test_training_changes_the_actor_and_the_critic(run):
    result, _, _ = run
    for name in ("actor", "critic"):
        before, after = result["initial_params"][name], TensorDict.from_module(result[name])
        assert not (before == after).all(), f"{name} parameters did not change"
        assert after.apply(lambda p: torch.isfinite(p).all(), batch_size=[]).all()


def test_model_honours_the_key_contract_on_a_native_layout():
    env = KitchenEnv(num_envs=3, levels="cramped_room", max_steps=8)  # 4x5, not 7x7
    actor, critic = train_custom_model.make_actor_critic(env)
    td = critic(actor(env.reset()))
    assert td["agents", "logits"].shape == (3, 2, 6)
    assert td["agents", "action"].shape == (3, 2) and td["agents", "action"].dtype == torch.int64
    assert td["agents", "action_log_prob"].shape == (3, 2)
    assert td["agents", "state_value"].shape == (3, 2, 1)
    with pytest.raises(ValueError, match="KitchenCNN expects"):
        critic.module(torch.zeros(3, 2, 7, 7, 26, dtype=torch.uint8))
