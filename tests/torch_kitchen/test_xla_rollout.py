"""The rollout inside one XLA program (`torch_kitchen.xla_rollout`): the kitchens stepped as a `KitchenEnv` steps
them with the actions it drew, the teams' networks (their graph layers and LSTMs too) as torch computes them, the
draws from each team's stream."""

import pytest
import torch
from tensordict.nn import TensorDictModuleBase
from test_rollout import assert_same_batches, env_and_policy
from torch.utils._pytree import tree_flatten
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.modules import set_recurrent_mode

from torch_kitchen.env import team_rows
from torch_kitchen.keys import ACTION, LOG_PROB, LOGITS, OBSERVATION, VALUE
from torch_kitchen.rollout import NEXT, KitchenCollector
from torch_kitchen.teams import acting_pass_of
from torch_kitchen.xla_rollout import XlaCollector
from trainers.rollout import make_collector


class Replay(TensorDictModuleBase):
    """A policy that writes, step after step, the policy outputs `out_keys` of recorded batches [B, T] (a recurrent
    one's next states among them)."""

    def __init__(self, batches, out_keys):
        super().__init__()
        self.in_keys, self.out_keys = [OBSERVATION], list(out_keys)
        self.steps = [batch[:, t] for batch in batches for t in range(batch.shape[1])]
        self.played = 0

    def forward(self, tensordict):
        step = self.steps[self.played]
        self.played += 1
        if any(key[0] == NEXT for key in self.out_keys) and NEXT not in tensordict.keys():
            tensordict.set((NEXT, "agents"), tensordict.get("agents").empty())  # with the agent dim, as the LSTM's
        for key in self.out_keys:
            tensordict.set(key, step.get(key).clone())
        return tensordict


def xla_batches(tmp_path, overrides, count=3):
    env, policy, config = env_and_policy(tmp_path, overrides)
    collector = XlaCollector(env, policy, env.batch_size.numel() * config.rollout_steps, -1)
    batches = iter(collector)
    return [next(batches).clone() for _ in range(count)], env, policy, config


# Episodes of 10 steps in batches of 16: they end inside a batch and across two (an LSTM's states start again there).
@pytest.mark.parametrize("overrides", [["architecture=mlp"],
                                       ["architecture=mlp", "runtime.teams=2", "levels=infinite"],
                                       ["architecture=ego_mlp", "runtime.teams=2", "levels=infinite"],
                                       ["architecture=mlp_lstm", "share_params=false", "runtime.teams=2"],
                                       ["architecture=gnn", "runtime.teams=2", "levels=infinite"],
                                       ["architecture=gnn_lstm"],
                                       ["architecture=mlp_lstm", "runtime.teams=2", "levels=infinite"]],
                         ids=["mlp", "mlp-2-teams", "ego_mlp-2-teams", "mlp_lstm-per-agent-2-teams", "gnn-2-teams",
                              "gnn_lstm", "mlp_lstm-2-teams"])
@pytest.mark.bitwise
def test_the_xla_rollout_steps_the_kitchens_as_the_kitchen_collector_does_with_its_actions(tmp_path, overrides):
    overrides = ["max_steps=10", *overrides]
    ours, env, _, config = xla_batches(tmp_path / "xla", overrides)
    assert ours[0]["next", "done"][:, :-1].any(), "an episode ends inside the first batch"

    twin, policy, _ = env_and_policy(tmp_path / "twin", overrides)
    replay = Replay(ours, policy.out_keys)
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


# A network per agent (the SK configs'): each agent's view through its own weights, as TorchRL's vmap runs them.
@pytest.mark.parametrize("overrides", [["architecture=mlp"], ["architecture=ego_mlp"], ["architecture=gnn"],
                                       ["architecture=gnn", "share_params=false"]],
                         ids=["mlp", "ego_mlp", "gnn", "gnn-per-agent"])
@pytest.mark.bitwise
def test_the_xla_policy_is_the_teams_networks_and_draws_from_their_streams(tmp_path, overrides):
    overrides = ["max_steps=10", *overrides, "runtime.teams=2", "levels=infinite"]
    batches, env, policy, _ = xla_batches(tmp_path / "first", overrides, count=2)
    for team, team_policy in enumerate(policy.policies):
        acting = acting_pass_of(team_policy)
        policy_net, value_net = acting.policy_net, acting.value_net
        if "share_params=false" in overrides:  # each agent its own weights: one agent's read for the other's shows
            weights = next(iter(acting.policy_net[0].params.values(True, True)))
            assert weights.shape[0] == 2 and not torch.equal(weights[0], weights[1])
        batch = batches[1][team_rows(team, env.team_size)]
        with torch.no_grad():
            torch.testing.assert_close(batch[LOGITS], policy_net(batch[OBSERVATION]), rtol=1e-5, atol=1e-5)
            torch.testing.assert_close(batch[VALUE], value_net(batch[OBSERVATION]), rtol=1e-5, atol=1e-5)
    assert_draws_from_the_teams_streams(tmp_path, overrides, batches)


def assert_draws_from_the_teams_streams(tmp_path, overrides, batches):
    """The batches' actions are draws from their logits, every action drawn, the same again for the same seed
    (runs of `overrides` under tmp_path) and others for another."""
    last = batches[-1]
    log_probs = last[LOGITS].log_softmax(-1).gather(-1, last[ACTION].unsqueeze(-1)).squeeze(-1)
    torch.testing.assert_close(last[LOG_PROB], log_probs)
    assert len(last[ACTION].unique()) == 6, "every action is drawn"

    again, _, _, _ = xla_batches(tmp_path / "again", overrides, count=len(batches))
    for ours, theirs in zip(batches, again):
        assert_same_batches(ours, theirs)
    other, _, _, _ = xla_batches(tmp_path / "other", [*overrides, "seed=1"], count=1)
    assert not torch.equal(other[0][ACTION], batches[0][ACTION]), "another seed draws other actions"


@pytest.mark.parametrize("architecture,teams,share", [("mlp_lstm", 2, "true"), ("gnn_lstm", 1, "true"),
                                                       ("mlp_lstm", 1, "false")])
@pytest.mark.bitwise
def test_the_xla_recurrent_policy_is_the_teams_lstms_and_draws_from_their_streams(tmp_path, architecture, teams,
                                                                                  share):
    overrides = ["max_steps=10", f"architecture={architecture}", f"runtime.teams={teams}", "levels=infinite",
                 f"share_params={share}"]
    batches, env, policy, _ = xla_batches(tmp_path / "first", overrides)
    for team, team_policy in enumerate(policy.policies):
        actor, critic = team_policy.module
        for network, out_key in ((actor.module[0], LOGITS), (critic, VALUE)):
            next_states = [key for key in network.out_keys if key[0] == NEXT]
            for batch in batches:
                rows = batch[team_rows(team, env.team_size)]
                with torch.no_grad():
                    # Step by step from the states the batch holds: the outputs and the states each step left.
                    for t in range(rows.shape[1]):
                        step = network(rows[:, t].select(*network.in_keys))
                        for key in [out_key, *next_states]:
                            torch.testing.assert_close(rows[:, t].get(key), step.get(key), rtol=1e-5, atol=1e-5)
                    # Over whole sequences from the batch's first states: the states are carried as the LSTM
                    # carries them, restarting where an episode starts, and from one batch to the next.
                    with set_recurrent_mode(True):
                        sequence = network(rows.select(*network.in_keys))
                torch.testing.assert_close(rows.get(out_key), sequence.get(out_key), rtol=1e-5, atol=1e-5)
    assert batches[0]["is_init"][:, 1:].any() and batches[1]["is_init"][:, 1:].any(), "episodes start inside batches"
    assert_draws_from_the_teams_streams(tmp_path, overrides, batches)


@pytest.mark.parametrize("overrides,kind", [
    (["architecture=mlp"], XlaCollector),
    (["architecture=ego_mlp"], XlaCollector),
    (["architecture=mlp_lstm"], XlaCollector),
    (["architecture=mlp", "share_params=false"], XlaCollector),
    (["architecture=mlp_lstm", "share_params=false"], XlaCollector),
    (["architecture=gnn"], XlaCollector),
    (["architecture=gnn_lstm"], XlaCollector),
    (["architecture=e3t_gnn", "algorithm=e3t"], KitchenCollector),
], ids=["mlp", "ego_mlp", "mlp_lstm", "mlp-per-agent", "mlp_lstm-per-agent", "gnn", "gnn_lstm", "e3t_gnn"])
def test_the_xla_kind_takes_the_models_it_can_run_and_leaves_the_others_to_the_kitchen_collector(
        tmp_path, overrides, kind):
    env, policy, config = env_and_policy(tmp_path, overrides)
    collector = make_collector(env, policy, env.batch_size.numel() * config.rollout_steps, kind="xla")
    assert type(collector) is kind
    collector.shutdown()


def test_the_xla_collector_refuses_a_recurrent_team_without_its_transforms_or_with_others(tmp_path):
    env, policy, config = env_and_policy(tmp_path, ["architecture=mlp_lstm"])
    frames = env.batch_size.numel() * config.rollout_steps
    with pytest.raises(ValueError, match="KitchenCollector"):
        XlaCollector(env.base_env, policy, frames)
    transforms = [transform.clone() for transform in env.transform]
    more = TransformedEnv(env.base_env, Compose(*transforms, InitTracker(init_key="started")))
    with pytest.raises(ValueError, match="KitchenCollector"):
        XlaCollector(more, policy, frames)


def test_the_program_reads_copies_in_xla_memory_not_the_teams_tensors(tmp_path):
    """On a GPU, the program's command buffers fail at its next call on inputs in torch's memory (BENCHMARKS.md,
    "A fourth lending"): what it reads from torch is copied into XLA's own buffers, so a tensor written after the
    hand-over leaves the program's input as it was."""
    env, policy, config = env_and_policy(tmp_path, ["architecture=mlp"])
    collector = XlaCollector(env, policy, env.batch_size.numel() * config.rollout_steps, -1)
    tensor = torch.arange(6.0)
    handed = collector._to_jax(tensor)
    assert handed.unsafe_buffer_pointer() != tensor.data_ptr()
    tensor += 1
    assert handed.tolist() == [0.0, 1.0, 2.0, 3.0, 4.0, 5.0]
