"""Training collects through the kitchens' own collector or TorchRL's, and learns the same either way."""

from test_ppo import tiny_config
from test_teams import assert_same_run

from trainers.ppo import train


def test_a_run_collecting_with_torchrls_collector_learns_what_the_kitchen_collector_learns(tmp_path):
    # Episodes of 10 steps in batches of 16: resets inside batches, and three updates.
    overrides = ("max_steps=10", "architecture=mlp_lstm")
    torchrl = train(tiny_config(tmp_path / "torchrl", "runtime.collector=torchrl", *overrides, updates=3))
    kitchen = train(tiny_config(tmp_path / "kitchen", *overrides, updates=3))
    assert_same_run(kitchen, torchrl)
