"""The rollout inside one XLA program (`torch_kitchen.xla_rollout`): the kitchens stepped as a `KitchenEnv` steps
them with the actions it drew, the teams' networks (their graph layers and LSTMs too) as torch computes them, the
draws from each team's stream; evaluation's seated teams and scripted cooks as they act outside it."""

import pytest
import torch
from scripted_cook import TWO_BOOTHS
from tensordict.nn import TensorDictModuleBase
from test_rollout import assert_same_batches, env_and_policy
from torch.utils._pytree import tree_flatten
from torchrl.envs import Compose, InitTracker, TransformedEnv
from torchrl.modules import set_recurrent_mode

from jax_env import parse_layout
from torch_kitchen.env import KitchenEnv, team_rows, with_transforms
from torch_kitchen.keys import ACTION, LOG_PROB, LOGITS, OBSERVATION, VALUE
from torch_kitchen.models import make_actor_critic
from torch_kitchen.partners.conventions import Convention
from torch_kitchen.partners.guide import TEACHER_PROBS, GuidedPolicy
from torch_kitchen.partners.pairing import make_seated_actor
from torch_kitchen.partners.scripted_cook import ScriptedCook, scripted_actor_critic
from torch_kitchen.rollout import NEXT, KitchenCollector
from torch_kitchen.teams import acting_pass_of
from torch_kitchen.xla_rollout import SeatedCollector, XlaCollector
from trainers.ppo.collection import make_collector, play_episodes


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


def seated_teams_and_kitchens():
    """Teams of every kind `SeatedCollector` plays (an MLP shared and one per agent, an agent-centred MLP, the GNN,
    the scripted cook of two conventions), their weights scaled so that each network acts as its likeliest action
    says, seated in 12 kitchens: 6 `TWO_BOOTHS` (each cook alone in a booth: it plans the same steps every time), 6
    of a corridor where the cooks walk and meet."""
    torch.manual_seed(0)
    actors = []
    for architecture, share in (("mlp", True), ("mlp", False), ("ego_mlp", True), ("gnn", True)):
        actor = make_actor_critic(architecture, (3, 5, 26), 16, share).actor
        with torch.no_grad():
            for parameter in actor.parameters():
                parameter.mul_(40.0)
        actors.append(actor)
    actors += [scripted_actor_critic().actor, scripted_actor_critic(Convention(move_order="EWSN")).actor]
    seating = torch.tensor([[0, 4], [5, 1], [2, 3], [4, 5], [3, 0], [5, 5]] * 2)
    actor = make_seated_actor(actors)
    actor.module[0].seat(seating)
    corridor = parse_layout("WPOXW\nB0 1W\nWWBWW", name="corridor")
    return actor, seating, [TWO_BOOTHS] * 6 + [corridor] * 6


def test_seated_teams_act_inside_xla_as_their_networks_and_cooks_do():
    actor, seating, grids = seated_teams_and_kitchens()
    env = KitchenEnv(12, levels=grids, max_steps=16, seed=1, pin_levels=True)
    collector = make_collector(env, actor, 12 * 8, 12 * 16, kind="xla")
    assert isinstance(collector, SeatedCollector)
    for batch in collector:  # two batches of 8 steps
        observation, logits = batch[OBSERVATION], batch[LOGITS]
        for team, member in enumerate(actor.module[0].actors):
            seats = seating[:, None].expand(-1, 8, -1) == team  # [12, 8, 2]
            network = member.module[0]
            if isinstance(network.module, ScriptedCook):
                own = network.module(observation)  # the torch cook, planned from its own floor tables
                torch.testing.assert_close(logits[seats], own[seats], rtol=0, atol=0)
            else:
                own = network(batch.select(OBSERVATION).clone()).get(LOGITS)[seats]
                # To float32 rounding of the sums behind each row, as large as its largest logit (the weights x40
                # make them thousands; a small logit of such a row is what is left of them): the same bound on an
                # AVX2 machine, whose kernels sum in another order, as on an AVX-512 one.
                rounding = 1e-5 * own.abs().amax(-1, keepdim=True)
                assert ((logits[seats] - own).abs() <= rounding).all(), (logits[seats] - own).abs().max()
        drawn = logits.gather(-1, batch[ACTION].unsqueeze(-1))
        assert torch.isfinite(drawn).all() and (drawn > logits.max(-1, keepdim=True).values - 30).all()
        torch.testing.assert_close(batch[LOG_PROB], torch.log_softmax(logits, -1).gather(
            -1, batch[ACTION].unsqueeze(-1)).squeeze(-1))
        assert (batch[VALUE] == 0).all()  # no critic plays


def test_seated_teams_play_the_same_episodes_inside_xla_where_their_actions_are_certain():
    """Networks that act as their likeliest action says, and cooks alone in booths, play the same episodes with either
    collector; a recurrent team (or E3T's), and kitchens whose levels are drawn per episode (a cook's floor would
    change inside a batch), are played by the kitchen collector."""
    actor, seating, grids = seated_teams_and_kitchens()
    outcomes = {}
    for kind in ("kitchen", "xla"):
        torch.manual_seed(5)
        env = KitchenEnv(12, levels=grids, max_steps=64, seed=1, pin_levels=True)
        outcomes[kind] = play_episodes(env, actor, 64, max_frames=12 * 32, kind=kind)
    cooks_meet = torch.zeros(12, dtype=torch.bool)
    cooks_meet[6:] = (seating[6:] >= 4).any(-1)  # in the corridor a cook steps or waits by a coin where they meet
    for name in ("deliveries", "visits", "events"):
        kitchen, xla = (getattr(outcomes[kind], name)[~cooks_meet] for kind in ("kitchen", "xla"))
        torch.testing.assert_close(xla, kitchen, rtol=0, atol=0)
    assert outcomes["xla"].deliveries[:6].sum() > 0  # the booths' cooks deliver

    recurrent = make_seated_actor([make_actor_critic("mlp_lstm", (3, 5, 26), 8, True).actor])
    recurrent.module[0].seat(torch.zeros(2, 2, dtype=torch.long))
    env = KitchenEnv(2, levels=grids[:2], max_steps=4, seed=1, pin_levels=True)
    env = with_transforms(env, recurrent.module[0].env_transforms())
    assert isinstance(make_collector(env, recurrent, 8, 8, kind="xla"), KitchenCollector)
    drawn = KitchenEnv(12, levels=grids, max_steps=4, seed=1)
    assert isinstance(make_collector(drawn, actor, 48, 48, kind="xla"), KitchenCollector)


def test_a_guided_learner_takes_the_teachers_draws_by_its_share_inside_xla():
    """DAgger's rollout inside XLA: every state labelled with the teacher's distribution as the cook gives it outside,
    on kitchens whose levels change per episode; a seat acts as the teacher with the guide's share (none: every
    action the learner's own draw; all: every action one the teacher may take), and the learner's log-probability
    stays that of its own draw. The share is the program's input, set before each batch."""
    torch.manual_seed(3)
    env = KitchenEnv(8, levels="infinite", max_steps=10, seed=2)
    learner = make_actor_critic("ego_mlp", env.obs_shape, 16, True)
    guided = GuidedPolicy(learner.acting_policy(), ScriptedCook(Convention(role="server")))
    collector = make_collector(env, guided, 8 * 16, kind="xla")
    assert isinstance(collector, XlaCollector)
    batches = iter(collector)
    for taking in (0.0, 1.0, 0.5):
        guided.teacher_share = taking
        batch = next(batches)
        assert batch[NEXT, "done"].any()  # episodes end inside the batches: new floors for the teacher
        labels = torch.softmax(ScriptedCook(Convention(role="server"))(batch[OBSERVATION]), -1)
        torch.testing.assert_close(batch[TEACHER_PROBS], labels)
        own = batch[LOGITS].log_softmax(-1).gather(-1, batch[ACTION].unsqueeze(-1)).squeeze(-1)
        taught = labels.gather(-1, batch[ACTION].unsqueeze(-1)).squeeze(-1)
        if taking == 0.0:
            torch.testing.assert_close(batch[LOG_PROB], own)
        elif taking == 1.0:
            assert (taught > 0).all()
            certain = labels.max(-1).values == 1
            assert certain.any() and torch.equal(batch[ACTION][certain], labels.argmax(-1)[certain])
        else:
            assert (batch[LOG_PROB] != own).any() and (taught == 0).any()  # some seats the teacher's, some not
