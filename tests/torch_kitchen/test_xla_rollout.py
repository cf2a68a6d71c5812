"""The rollout inside one XLA program (`torch_kitchen.xla_rollout`): the kitchens stepped as a `KitchenEnv` steps
them with the actions it drew, the teams' networks as torch computes them, the draws from each team's stream."""

import pytest
import torch
from tensordict.nn import TensorDictModuleBase
from test_rollout import assert_same_batches, env_and_policy
from torch.utils._pytree import tree_flatten

from torch_kitchen.env import team_rows
from torch_kitchen.keys import ACTION, LOG_PROB, LOGITS, OBSERVATION, VALUE
from torch_kitchen.rollout import KitchenCollector
from torch_kitchen.teams import stackable_acting
from torch_kitchen.xla_rollout import XlaCollector
from trainers.rollout import make_collector


class Replay(TensorDictModuleBase):
    """A policy that writes, step after step, the policy outputs of recorded batches [B, T]."""

    def __init__(self, batches):
        super().__init__()
        self.in_keys, self.out_keys = [OBSERVATION], [LOGITS, ACTION, LOG_PROB, VALUE]
        self.steps = [batch[:, t] for batch in batches for t in range(batch.shape[1])]
        self.played = 0

    def forward(self, tensordict):
        step = self.steps[self.played]
        self.played += 1
        for key in self.out_keys:
            tensordict.set(key, step.get(key).clone())
        return tensordict


def xla_batches(tmp_path, overrides, count=3):
    env, policy, config = env_and_policy(tmp_path, overrides)
    collector = XlaCollector(env, policy, env.batch_size.numel() * config.rollout_steps, -1)
    batches = iter(collector)
    return [next(batches).clone() for _ in range(count)], env, policy, config


# Episodes of 10 steps in batches of 16: they end inside a batch and across two.
@pytest.mark.parametrize("overrides", [["architecture=mlp"],
                                       ["architecture=mlp", "runtime.teams=2", "levels=infinite"],
                                       ["architecture=ego_mlp", "runtime.teams=2", "levels=infinite"]],
                         ids=["mlp", "mlp-2-teams", "ego_mlp-2-teams"])
def test_the_xla_rollout_steps_the_kitchens_as_the_kitchen_collector_does_with_its_actions(tmp_path, overrides):
    overrides = ["max_steps=10", *overrides]
    ours, env, _, config = xla_batches(tmp_path / "xla", overrides)
    assert ours[0]["next", "done"].any(), "an episode ends inside the first batch"

    twin, _, _ = env_and_policy(tmp_path / "twin", overrides)
    replay = Replay(ours)
    frames = env.batch_size.numel() * config.rollout_steps
    collector = KitchenCollector(twin, replay, frames, len(ours) * frames)
    replay.played = 0  # the collector's look at the policy's outputs drew one step
    theirs = [batch.clone() for batch in collector]
    for mine, kitchen in zip(ours, theirs):
        assert mine.names == kitchen.names and mine.device == kitchen.device
        assert_same_batches(mine, kitchen)
    # The env is left where the batches ended: its checkpoint and next reset are the stepped kitchens'.
    for team in range(env.teams):
        ours_state, spec = tree_flatten(env.team_state(team))
        twin_state, twin_spec = tree_flatten(twin.team_state(team))
        assert ours_state and spec == twin_spec
        assert all(torch.equal(a, b) if isinstance(a, torch.Tensor) else a == b for a, b in zip(ours_state, twin_state))


@pytest.mark.parametrize("architecture", ["mlp", "ego_mlp"])
def test_the_xla_policy_is_the_teams_networks_and_draws_from_their_streams(tmp_path, architecture):
    overrides = ["max_steps=10", f"architecture={architecture}", "runtime.teams=2", "levels=infinite"]
    batches, env, policy, _ = xla_batches(tmp_path / "first", overrides, count=2)
    networks = stackable_acting(list(policy.policies))
    for team, (policy_net, value_net) in enumerate(networks):
        batch = batches[1][team_rows(team, env.team_size)]
        with torch.no_grad():
            torch.testing.assert_close(batch[LOGITS], policy_net(batch[OBSERVATION]), rtol=1e-5, atol=1e-5)
            torch.testing.assert_close(batch[VALUE], value_net(batch[OBSERVATION]), rtol=1e-5, atol=1e-5)
    log_probs = batches[1][LOGITS].log_softmax(-1).gather(-1, batches[1][ACTION].unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(batches[1][LOG_PROB], log_probs)
    assert len(batches[1][ACTION].unique()) == 6, "every action is drawn"

    again, _, _, _ = xla_batches(tmp_path / "again", overrides, count=2)
    for ours, theirs in zip(batches, again):
        assert_same_batches(ours, theirs)
    other, _, _, _ = xla_batches(tmp_path / "other", [*overrides, "seed=1"], count=1)
    assert not torch.equal(other[0][ACTION], batches[0][ACTION]), "another seed draws other actions"


@pytest.mark.parametrize("architecture,kind", [("mlp", XlaCollector), ("ego_mlp", XlaCollector),
                                               ("mlp_lstm", KitchenCollector), ("gnn", KitchenCollector)])
def test_the_xla_kind_takes_the_models_it_can_run_and_leaves_the_others_to_the_kitchen_collector(
        tmp_path, architecture, kind):
    env, policy, config = env_and_policy(tmp_path, [f"architecture={architecture}"])
    collector = make_collector(env, policy, env.batch_size.numel() * config.rollout_steps, kind="xla")
    assert type(collector) is kind
    collector.shutdown()
