"""The trainer's device path, checked on a CPU: what a GPU would run compiles whole, recompiles nothing across
updates, and makes the host wait for nothing inside a collection step or a minibatch."""

import contextlib

import pytest
import torch
import torch._dynamo
from op_audit import OpAudit
from tensordict.nn import set_interaction_type
from test_ppo import team_and_minibatch, tiny_config
from torch._dynamo.utils import counters
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import set_recurrent_mode

from torch_kitchen import sparse_linear
from torch_kitchen.keys import OBSERVATION
from torch_kitchen.onednn_linear import device_path
from trainers.ppo.collection import make_collector
from trainers.ppo.loop import train
from trainers.ppo.runtime import Learner, team_policy
from trainers.ppo.team import build_team, make_env


def test_the_loss_forward_and_the_acting_pass_compile_without_a_graph_break(tmp_path):
    team, minibatch = team_and_minibatch(tiny_config(tmp_path), tmp_path)
    torch._dynamo.reset()
    with device_path():
        loss = torch._dynamo.explain(team.loss_module)(minibatch.clone())
        acting = torch._dynamo.explain(team.policy)(minibatch[:, 0].clone())
    assert loss.graph_break_count == 0, [str(reason.reason)[:200] for reason in loss.break_reasons]
    assert acting.graph_break_count == 0, [str(reason.reason)[:200] for reason in acting.break_reasons]


def test_the_rollouts_acting_pass_on_plain_tensors_compiles_without_a_graph_break(tmp_path):
    """What `KitchenCollector` calls at every step (`TeamPolicy.act`'s pass, observations in, logits, actions,
    log-probabilities and values out) is one graph: ready to be replayed whole."""
    config = tiny_config(tmp_path)
    team, minibatch = team_and_minibatch(config, tmp_path)
    policy = team_policy(config, [team])
    assert policy.acts_on_observation
    torch._dynamo.reset()
    with device_path():
        acting = torch._dynamo.explain(policy.passes[0])(minibatch[:, 0].get(OBSERVATION).clone())
    reasons = [str(reason.reason)[:200] for reason in acting.break_reasons]
    assert acting.graph_count == 1 and acting.graph_break_count == 0, reasons


@pytest.mark.parametrize("kernels", ["device_path", "cpu"])
def test_a_compiled_minibatch_step_is_the_eager_one_to_float_rounding(tmp_path, kernels, monkeypatch):
    """On the device path (torch's own products, as a GPU runs them), and with the CPU's kernels, whose sparse first
    layer a compiled graph calls as one operator (`sparse_input_linear`)."""
    products = device_path() if kernels == "device_path" else contextlib.nullcontext()
    eager, minibatch = team_and_minibatch(tiny_config(tmp_path / "eager"), tmp_path / "eager")
    compiled_config = tiny_config(tmp_path / "compiled", "runtime.compile_update=true")
    compiled, _ = team_and_minibatch(compiled_config, tmp_path / "compiled")
    for mine, theirs in zip(compiled.parameters, eager.parameters):
        assert torch.equal(mine, theirs)  # the same seed builds the same weights
    with products, set_recurrent_mode(True), set_exploration_type(ExplorationType.RANDOM):
        eager_losses = Learner(eager.config, [eager]).step(minibatch.clone())
        searched = []
        monkeypatch.setattr(sparse_linear, "nonzero_entries", lambda *args: searched.append(args[0].shape) or
                            sparse_linear.NonZeroEntries(*args))
        compiled_losses = Learner(compiled_config, [compiled]).step(minibatch.clone())
    # The actor's and the critic's first layers, forward and backward; none on the device path.
    assert len(searched) == (0 if kernels == "device_path" else 4), searched
    for key in ("loss_objective", "loss_critic", "loss_entropy", "grad_norm"):
        torch.testing.assert_close(compiled_losses[key], eager_losses[key], rtol=1e-5, atol=1e-6, msg=key)
    moved = 0
    before, _ = team_and_minibatch(tiny_config(tmp_path / "before"), tmp_path / "before")
    for mine, theirs, before in zip(compiled.parameters, eager.parameters, before.parameters):
        torch.testing.assert_close(mine, theirs, rtol=1e-5, atol=1e-6)
        moved += not torch.equal(mine, before)
    assert moved == len(eager.parameters)  # both took a step


@pytest.mark.parametrize("share_params", ["false", "true"])
def test_compiled_training_recompiles_nothing_as_the_learning_rate_and_shaping_anneal(tmp_path, share_params):
    """Graph breaks only where torch itself puts them (around the optimizer's step): the loss and its gradient are
    one graph; the annealed learning rate is a tensor and the shaping weight acts outside the step, so no update
    after the first compiles. With one network per agent (the SK configs'), which TorchRL runs under vmap, and with
    shared networks, whose sparse first layers are operators of the graph: their inputs' entries, as many as the
    minibatch has, stay outside it."""
    config = tiny_config(tmp_path, "runtime.compile_update=true", "ppo.anneal_lr=true", "ppo.shaping_weight=1",
                         "ppo.shaping_anneal_steps=200", f"share_params={share_params}", updates=3)
    torch._dynamo.reset()
    counters.clear()
    graphs, rates = [], []

    def on_update(update, metrics):
        graphs.append(counters["stats"]["unique_graphs"])
        rates.append(metrics["charts/learning_rate"])

    train(config, on_update=on_update)
    assert len(set(rates)) == 3 and graphs[0] > 0
    assert graphs == [graphs[0]] * 3, graphs
    assert counters["graph_break"], "the optimizer's own breaks are expected"
    for reason in counters["graph_break"]:
        assert "Called `torch._dynamo.graph_break()`" in reason, reason


def test_a_collection_step_and_a_minibatch_make_the_host_wait_for_nothing(tmp_path):
    """Eager, on the device path: neither a collection step nor a minibatch reads anything back from the device
    (TorchRL's own check that the entropy is finite is left out: `entropy_without_host_check`). Dispatch modes see
    eager operations, not a compiled graph's kernels."""
    config = tiny_config(tmp_path)
    env = make_env(config)
    team = build_team(config, config.run_path, env, 0)
    collector = make_collector(env, team.policy, 4 * 3, -1)  # 3 steps of the 4 kitchens per batch
    with device_path():
        batches = iter(collector)
        next(batches)
        with OpAudit() as collection:
            next(batches)
        collector.shutdown()
        team, minibatch = team_and_minibatch(tiny_config(tmp_path / "update"), tmp_path / "update")
        with set_recurrent_mode(True), set_interaction_type(team.loss_module.deterministic_sampling_mode):
            learner = Learner(team.config, [team])
            learner.step(minibatch.clone())  # builds Adam's state
            with OpAudit() as update:
                learner.step(minibatch.clone())
    assert collection.launches > 0 and collection.syncs == 0, collection.summary()
    assert update.launches > 0 and update.syncs == 0 and update.host_tensors == 0, update.summary()


@pytest.mark.slow
def test_the_teams_stacked_step_compiles_to_the_eager_one_and_launches_fewer_kernels_than_two_teams(tmp_path):
    """Three teams' minibatch step as one (`stacked_gradients`, the GPU's way), eager and compiled, moves every
    team's weights as the other does; eager, it launches fewer kernels than two teams' steps one after another."""
    def teams_and_minibatches(name, *overrides):
        return zip(*[team_and_minibatch(tiny_config(tmp_path / name / str(seed), f"seed={seed}", *overrides),
                                        tmp_path / name / str(seed)) for seed in range(3)])

    eager_teams, minibatches = teams_and_minibatches("eager")
    compiled_teams, _ = teams_and_minibatches("compiled", "runtime.compile_update=true")
    apart_teams, _ = teams_and_minibatches("apart")
    minibatches = torch.stack(minibatches)
    torch._dynamo.reset()
    with device_path(), set_recurrent_mode(True):
        eager_step = Learner(eager_teams[0].config, eager_teams).step
        eager_losses = eager_step(minibatches.clone())
        compiled_losses = Learner(compiled_teams[0].config, compiled_teams).step(minibatches.clone())
        for key in ("loss_objective", "loss_critic", "loss_entropy", "grad_norm"):
            assert compiled_losses[key].shape == (3,)
            torch.testing.assert_close(compiled_losses[key], eager_losses[key], rtol=1e-5, atol=1e-6, msg=key)
        for compiled, eager in zip(compiled_teams, eager_teams):
            for mine, theirs in zip(compiled.parameters, eager.parameters):
                torch.testing.assert_close(mine, theirs, rtol=1e-5, atol=1e-6)

        with OpAudit() as stacked:
            eager_step(minibatches.clone())
        with OpAudit() as apart:
            for team, minibatch in zip(apart_teams, minibatches):
                Learner(team.config, [team]).step(minibatch.clone())
    # The loss's and backward's kernels once for all teams; per team its clipping and Adam step.
    assert stacked.syncs == 0 and stacked.launches < 2 * apart.launches / 3, (stacked.summary(), apart.summary())


def test_a_run_resumed_with_the_compiled_update_recompiles_nothing_either(tmp_path):
    """A checkpoint saved without `compile_update` holds the learning rate as a number: resumed with it, the rate
    becomes a tensor again, so annealing it still changes a value rather than the graph."""
    train(tiny_config(tmp_path, "ppo.anneal_lr=true", updates=1))
    resumed = tiny_config(tmp_path, "ppo.anneal_lr=true", "runtime.compile_update=true", updates=4)
    torch._dynamo.reset()
    counters.clear()
    graphs = []
    train(resumed, resume=True, on_update=lambda update, metrics: graphs.append(counters["stats"]["unique_graphs"]))
    assert len(graphs) == 3 and graphs == [graphs[0]] * 3, graphs
