"""One test per TorchRL hook of `torch_kitchen.torchrl_internals`: a TorchRL release that changes one fails here."""

import copy
import functools

import pytest
import torch
from op_audit import OpAudit
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.summary.writer import event_file_writer
from tensordict import TensorDict
from tensordict.nn import TensorDictModule
from torch import nn
from torchrl.modules import ProbabilisticActor, ValueOperator
from torchrl.objectives import ClipPPOLoss

from torch_kitchen.models.networks import make_encoder
from torch_kitchen.torchrl_internals import (
    TEMPLATE,
    MultiAgentNet,
    PurgingTensorboardLogger,
    entropy_without_host_check,
)


def test_multi_agent_net_builds_one_network_per_agent_through_build_single_net():
    torch.manual_seed(0)
    net = MultiAgentNet(lambda: nn.Linear(3, 2), (3,), share_params=False)
    inputs = torch.randn(5, 2, 3)
    outputs = net(inputs)
    assert outputs.shape == (5, 2, 2)
    # Each agent's slice goes through its own stacked parameters.
    for agent in range(2):
        weight, bias = net.params["weight"][agent], net.params["bias"][agent]
        torch.testing.assert_close(outputs[:, agent], inputs[:, agent] @ weight.T + bias)
    assert not torch.allclose(net.params["weight"][0], net.params["weight"][1])
    shared = MultiAgentNet(lambda: nn.Linear(3, 2), (3,), share_params=True)
    assert shared.params["weight"].shape == (2, 3)


def test_multi_agent_net_checks_its_inputs_through_pre_forward_check():
    net = MultiAgentNet(lambda: nn.Linear(3, 2), (3,))
    with pytest.raises(ValueError, match=r"expects inputs \[..., 2, 3\], got \[5, 2, 4\]"):
        net(torch.randn(5, 2, 4))

    class Doubling(MultiAgentNet):
        def check_input(self, inputs):
            return 2 * super().check_input(inputs)

    doubled = Doubling(lambda: nn.Identity(), (3,))
    inputs = torch.randn(4, 2, 3)
    torch.testing.assert_close(doubled(inputs), 2 * inputs)


def test_a_shared_net_runs_get_stateful_nets_network_on_its_own_parameters():
    torch.manual_seed(0)
    net = MultiAgentNet(lambda: nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 2)), (3,))
    inputs = torch.randn(5, 2, 3)
    with net.params.to_module(net._empty_net, preserve_module_state=False):  # MultiAgentNetBase's own way
        expected = net._empty_net(inputs)
    assert torch.equal(net(inputs), expected)
    assert {id(p) for p in net.shared_net().parameters()} == {id(p) for p in net.parameters()}  # not copies
    assert list(net.state_dict()) == [f"params.{key}" for key in ("0.weight", "0.bias", "2.weight", "2.bias")]

    copied = copy.deepcopy(net)
    with torch.no_grad():
        net.params["0", "bias"].add_(1.0)  # in place, as an optimizer steps
    changed = net(inputs)
    assert not torch.equal(changed, expected)
    assert torch.equal(copied(inputs), expected)  # a copy runs on its own parameters
    copied.load_state_dict(net.state_dict())
    assert torch.equal(copied(inputs), changed)
    moved = net.to(torch.float64)  # a move may replace the parameters: the network follows
    assert moved(inputs.double()).dtype == torch.float64


def test_a_shared_net_runs_parameters_swapped_in_from_outside():
    """A functional call (tensordict's `to_module`, also under vmap over stacked parameters) swaps other parameters
    into `params`; the network built on the net's own must not run in their place."""
    torch.manual_seed(0)
    build = lambda: nn.Sequential(nn.Linear(3, 4), nn.ReLU(), nn.Linear(4, 2))  # noqa: E731
    net, other, third = (MultiAgentNet(build, (3,)) for _ in range(3))
    inputs = torch.randn(5, 2, 3)
    own = net(inputs)
    with TensorDict.from_module(other).to_module(net):
        torch.testing.assert_close(net(inputs), other(inputs))
    assert torch.equal(net(inputs), own)  # its own again
    stacked = torch.stack([TensorDict.from_module(other), TensorDict.from_module(third)])

    def swapped(parameters, x):
        with parameters.to_module(net):
            return net(x)

    by_net = torch.vmap(swapped, (0, None))(stacked, inputs)
    torch.testing.assert_close(by_net, torch.stack([other(inputs), third(inputs)]))


def test_the_ppo_loss_takes_the_closed_form_entropy_without_a_host_read():
    """TorchRL's eager check of the entropy reads the device (`_local_scalar_dense`); the hook's loss reads nothing
    and gives the same entropy and losses."""
    torch.manual_seed(0)
    actor = ProbabilisticActor(TensorDictModule(nn.Linear(3, 6), ["observation"], ["logits"]), ["logits"],
                               distribution_class=torch.distributions.Categorical, return_log_prob=True)
    critic = ValueOperator(nn.Linear(3, 1), ["observation"])
    batch = TensorDict({"observation": torch.randn(8, 3), "action": torch.randint(6, (8,)),
                        "action_log_prob": torch.full((8,), -1.8), "advantage": torch.randn(8, 1),
                        "value_target": torch.randn(8, 1)}, batch_size=[8])
    theirs, ours = ClipPPOLoss(actor, critic), ClipPPOLoss(actor, critic)
    entropy_without_host_check(ours)
    with OpAudit() as checked:
        expected = theirs(batch.clone())
    with OpAudit() as unchecked:
        got = ours(batch.clone())
    assert checked.sync_ops() == {"_local_scalar_dense": 1} and unchecked.syncs == 0, unchecked.summary()
    for key in ("entropy", "loss_entropy", "loss_objective", "loss_critic"):
        torch.testing.assert_close(got[key], expected[key], rtol=0, atol=0)


@pytest.mark.parametrize("share_params", [True, False])
def test_the_template_network_stays_out_of_state_dicts(share_params):
    """torch-geometric's GATConv saves entries even in MultiAgentNetBase's parameter-less template."""
    build = functools.partial(make_encoder, "gnn", (4, 5, 26), 8)
    net = MultiAgentNet(build, (4, 5, 26), share_params=share_params)
    state = net.state_dict()
    assert hasattr(net, TEMPLATE)
    assert state and not any(TEMPLATE in key for key in state)
    other = MultiAgentNet(build, (4, 5, 26), share_params=share_params)
    other.load_state_dict(state)
    observation = torch.rand(3, 2, 4, 5, 26)
    torch.testing.assert_close(other(observation), net(observation))


def test_the_tensorboard_logger_purges_events_at_and_after_the_purge_step(tmp_path, monkeypatch):
    # The two event files as a long test session names them when opened in one second: `.9` then `.10`, which
    # sort the other way round.
    monkeypatch.setattr(event_file_writer, "_global_uid", event_file_writer.AtomicCounter(9))
    first = PurgingTensorboardLogger("tensorboard", str(tmp_path))
    for step in range(1, 6):
        first.log_scalar("x", float(step), step=step)
    first.experiment.close()
    resumed = PurgingTensorboardLogger("tensorboard", str(tmp_path), purge_step=3)
    for step in (3, 4):
        resumed.log_scalar("x", 10.0 * step, step=step)
    resumed.experiment.close()
    events = EventAccumulator(str(tmp_path / "tensorboard"))
    events.Reload()
    assert [(event.step, event.value) for event in events.Scalars("x")] == [(1, 1.0), (2, 2.0), (3, 30.0), (4, 40.0)]
