"""Training collects through the kitchens' own collector or TorchRL's, and learns the same either way; or with its
teams acting inside XLA, a run as deterministic and resumable as the others."""

import pytest
from test_ppo import tiny_config
from test_teams import assert_same_run

from trainers.checkpoint import load_checkpoint
from trainers.ppo.loop import train, train_teams
from trainers.ppo.team import team_configs
from trainers.train_command import main


@pytest.mark.bitwise
def test_a_run_collecting_with_torchrls_collector_learns_what_the_kitchen_collector_learns(tmp_path):
    # Episodes of 10 steps in batches of 16: resets inside batches, and three updates.
    overrides = ("max_steps=10", "architecture=mlp_lstm")
    torchrl = train(tiny_config(tmp_path / "torchrl", "runtime.collector=torchrl", *overrides, updates=3))
    kitchen = train(tiny_config(tmp_path / "kitchen", "runtime.collector=kitchen", *overrides, updates=3))
    assert_same_run(kitchen, torchrl)


@pytest.mark.bitwise
def test_a_run_collecting_inside_xla_resumes_as_it_ran_and_its_teams_learn_as_their_seeds_alone(tmp_path):
    overrides = ("runtime.collector=xla", "max_steps=10", "checkpoint_every=1")
    teams = train_teams(team_configs(tiny_config(tmp_path / "teams", "runtime.teams=2", *overrides, updates=3)))

    def crash_at_update_2(update, metrics):
        if update == 2:
            raise RuntimeError("killed")

    crashed = tiny_config(tmp_path / "single", "seed=1", *overrides, updates=3)
    with pytest.raises(RuntimeError, match="killed"):
        train(crashed, on_update=crash_at_update_2)
    assert load_checkpoint(crashed.run_path)["update"] == 1
    assert main(["--resume", str(crashed.run_path)]) == 0
    assert_same_run(teams[1], crashed.run_path)
