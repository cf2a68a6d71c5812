"""`accelerate_cpu`: plain models until it runs; then the CPU kernels, with the same parameters and results."""

import pytest
import torch
from tensordict import TensorDict
from tiny import infinite_observations
from torch import nn

from torch_kitchen.cpu_kernels import CPU_TWINS, accelerate_cpu
from torch_kitchen.models import make_actor_critic


@pytest.fixture(scope="module")
def observations() -> torch.Tensor:
    """Real Infinite Kitchen observations, uint8 [64, 2, 7, 7, 26]."""
    return infinite_observations(64, seed=0)  # test_sparse_linear's: made once per process


@pytest.mark.parametrize("architecture", ["mlp", "ego_mlp", "gnn", "mlp_lstm", "e3t_mlp"])
@pytest.mark.parametrize("share_params", [True, False])
def test_an_accelerated_model_is_the_plain_one_with_cpu_kernels(architecture, share_params, observations):
    torch.manual_seed(0)
    plain = make_actor_critic(architecture, hidden=32, share_params=share_params)
    torch.manual_seed(0)
    fast = make_actor_critic(architecture, hidden=32, share_params=share_params)
    printed = repr(fast.critic)
    assert not any(twin.__name__ in printed for twin in CPU_TWINS.values())  # built plain
    parameters = list(fast.critic.parameters())
    accelerate_cpu(fast.actor, fast.critic)
    assert all(a is b for a, b in zip(fast.critic.parameters(), parameters))  # the optimizer's, still
    assert fast.critic.state_dict().keys() == plain.critic.state_dict().keys()
    if architecture in ("mlp", "ego_mlp") and share_params:  # the encoders' first layer has its sparse twin
        assert any(type(module).__name__.startswith("Sparse") for module in fast.critic.module[0].module.shared_net()
                   .modules())

    batch = TensorDict({("agents", "observation"): observations, "is_init": torch.ones(64, 1, dtype=torch.bool)},
                       batch_size=[64])
    values = {}
    for name, model in (("plain", plain), ("fast", fast)):
        out = model.critic(batch.clone())["agents", "state_value"]
        out.sum().backward()
        values[name] = out, [parameter.grad for parameter in model.critic.parameters()]
    torch.testing.assert_close(values["fast"][0], values["plain"][0], rtol=1e-5, atol=1e-5)
    for fast_grad, plain_grad in zip(values["fast"][1], values["plain"][1]):
        torch.testing.assert_close(fast_grad, plain_grad, rtol=1e-4, atol=1e-5)


def test_a_user_model_of_torch_layers_gets_them_too():
    model = nn.Sequential(nn.Linear(8, 300), nn.ReLU(), nn.Linear(300, 2))
    before = model(torch.ones(4096, 8))
    accelerate_cpu(model)
    assert type(model[0]).__name__ == "OneDNNLinear"
    torch.testing.assert_close(model(torch.ones(4096, 8)), before)
