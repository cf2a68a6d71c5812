"""The in-place rollout (`torch_kitchen.rollout`) gives the batches TorchRL's Collector gives, bit for bit."""

import pytest
import torch
from tiny import TINY
from torchrl.collectors import Collector
from torchrl.envs.utils import ExplorationType

from torch_kitchen.rollout import KitchenCollector
from trainers.config.compose import load_config
from trainers.ppo.runtime import team_policy
from trainers.ppo.team import build_teams, team_configs


def env_and_policy(tmp_path, overrides):
    """The env and acting policy `trainers.ppo.loop.train_teams` builds for a tiny config's teams."""
    config = load_config(None, [*TINY, f"run_dir={tmp_path}", "total_steps=1e4", *overrides])
    configs = team_configs(config)
    teams, env = build_teams(configs, [team.run_path for team in configs])
    return env, team_policy(config, teams), config


def torchrl_collector(env, policy, frames):
    return Collector(env, policy, frames_per_batch=frames, total_frames=3 * frames, return_same_td=True,
                     exploration_type=ExplorationType.RANDOM, auto_register_policy_transforms=False,
                     track_traj_ids=False)


# Episodes of 10 steps in batches of 16: they end inside a batch and across two.
@pytest.mark.parametrize("overrides", [
    ["architecture=mlp"],
    ["architecture=mlp", "runtime.teams=3", "levels=infinite"],
    ["architecture=mlp_lstm"],
    ["architecture=gnn", "runtime.teams=2"],
    ["algorithm=e3t", "architecture=e3t_mlp"],
], ids=["mlp", "mlp-3-teams", "lstm", "gnn-2-teams", "e3t"])
@pytest.mark.bitwise
def test_the_kitchen_collector_collects_the_batches_of_torchrls_collector(tmp_path, overrides):
    overrides = ["max_steps=10", *overrides]
    env, policy, config = env_and_policy(tmp_path / "torchrl", overrides)
    frames = env.batch_size.numel() * config.rollout_steps
    expected = [batch.clone() for batch in torchrl_collector(env, policy, frames)]
    env, policy, _ = env_and_policy(tmp_path / "kitchen", overrides)
    collector = KitchenCollector(env, policy, frames, 3 * frames)
    got = [batch.clone() for batch in collector]
    assert len(got) == len(expected) == 3
    assert got[0]["next", "done"].any(), "an episode ends inside the first batch"
    for ours, theirs in zip(got, expected):
        assert ours.batch_size == theirs.batch_size
        assert set(ours.keys(True, True)) == set(theirs.keys(True, True))
        assert_same_batches(ours, theirs)


def assert_same_batches(ours, theirs):
    """The same entries, bit for bit, in TensorDicts of the same batch sizes (the agents' dim included)."""
    assert set(ours.keys(True)) == set(theirs.keys(True))
    for key in theirs.keys(True):
        if isinstance(theirs.get(key), torch.Tensor):
            assert torch.equal(ours.get(key), theirs.get(key)), key
        else:
            assert ours.get(key).batch_size == theirs.get(key).batch_size, key


@pytest.mark.parametrize("architecture", ["mlp", "mlp_lstm"])
@pytest.mark.bitwise
def test_env_rollout_is_torchrls_rollout_and_continues_where_it_ended(tmp_path, architecture):
    """`env.rollout(T, policy, break_when_any_done=False)`, then continued with `auto_reset=False` from the last
    step's successor (TorchRL's documented loop), gives what TorchRL's own `EnvBase.rollout` gives."""
    overrides = ["max_steps=10", f"architecture={architecture}"]
    rollouts = {}
    for name, rollout in (("torchrl", lambda env, *a, **k: type(env).__mro__[1].rollout(env, *a, **k)),
                          ("kitchen", lambda env, *a, **k: env.rollout(*a, **k))):
        env, policy, _ = env_and_policy(tmp_path / name, overrides)
        first = rollout(env, 12, policy, break_when_any_done=False)
        second = rollout(env, 12, policy, break_when_any_done=False, auto_reset=False,
                         tensordict=env.step_mdp(first[..., -1]))
        rollouts[name] = first, second
    for ours, theirs in zip(rollouts["kitchen"], rollouts["torchrl"]):
        assert ours.batch_size == theirs.batch_size == (4, 12)
        assert set(ours.keys(True, True)) == set(theirs.keys(True, True))
        assert_same_batches(ours, theirs)
