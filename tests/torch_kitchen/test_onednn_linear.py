import pytest
import torch
from tensordict import TensorDict
from torch import nn

from torch_kitchen import onednn_linear
from torch_kitchen.cpu_kernels import accelerate_cpu
from torch_kitchen.models import make_actor_critic
from torch_kitchen.models.networks import make_head
from torch_kitchen.onednn_linear import OneDNNLinear, onednn_available

pytestmark = pytest.mark.skipif(not onednn_available(), reason="this torch has no oneDNN")


def _pair(in_features: int, out_features: int, bias: bool = True) -> tuple[nn.Linear, OneDNNLinear]:
    torch.manual_seed(0)
    plain = nn.Linear(in_features, out_features, bias=bias)
    onednn = OneDNNLinear(in_features, out_features, bias=bias)
    onednn.load_state_dict(plain.state_dict())
    return plain, onednn


def _took_onednn(out: torch.Tensor) -> bool:
    """Whether `out` (possibly reshaped after the product) came from `OneDNNProduct`."""
    node = out.grad_fn
    while node is not None and node.name() == "ViewBackward0":
        node = node.next_functions[0][0]
    return node is not None and node.name() == "OneDNNProductBackward"


@pytest.mark.parametrize("bias", [True, False])
def test_forward_and_every_gradient_equal_nn_linear_to_rounding(bias, monkeypatch):
    monkeypatch.setattr(onednn_linear, "ONEDNN_MIN_PRODUCT", 0)  # oneDNN at any size
    plain, onednn = _pair(48, 24, bias)
    x = torch.randn(5, 7, 48)
    x_plain, x_onednn = x.clone().requires_grad_(), x.clone().requires_grad_()
    grad_out = torch.randn(5, 7, 24)
    expected, out = plain(x_plain), onednn(x_onednn)
    expected.backward(grad_out)
    out.backward(grad_out)
    assert out.shape == (5, 7, 24)
    assert _took_onednn(out)  # oneDNN's path, not the fallback
    torch.testing.assert_close(out, expected)
    torch.testing.assert_close(x_onednn.grad, x_plain.grad)
    torch.testing.assert_close(onednn.weight.grad, plain.weight.grad)
    if bias:
        torch.testing.assert_close(onednn.bias.grad, plain.bias.grad)


def test_other_dtypes_and_a_torch_without_onednn_take_torchs_product(monkeypatch):
    plain, onednn = _pair(16, 8)
    x = torch.randn(4, 16, dtype=torch.float64)
    assert not _took_onednn(onednn.double()(x))
    torch.testing.assert_close(onednn(x), plain.double()(x))
    monkeypatch.setattr(onednn_linear, "_ONEDNN", False)
    assert not _took_onednn(onednn.float()(x.float()))
    torch.testing.assert_close(onednn(x.float()), plain.float()(x.float()))


def test_small_products_take_torchs_own_and_large_ones_onednn():
    # Acting in 16 kitchens (32 rows) and a minibatch of 1,024 rows at hidden 64, against a minibatch of 8,192.
    plain, onednn = _pair(64, 64)
    for rows, expected in [(32, False), (1024, False), (8192, True)]:
        x = torch.randn(rows, 64)
        out = onednn(x)
        assert _took_onednn(out) is expected, rows
        torch.testing.assert_close(out, plain(x))


def test_it_is_a_linear_layer_to_checkpoints():
    plain, onednn = _pair(12, 3)
    assert isinstance(onednn, nn.Linear)
    assert onednn.state_dict().keys() == plain.state_dict().keys()


def test_accelerate_cpu_gives_the_models_dense_layers_to_it():
    head = make_head(32, 6, 0.01, layer_norm=False)
    assert all(type(layer) is nn.Linear for layer in head if isinstance(layer, nn.Linear))
    accelerate_cpu(head)
    assert all(type(layer) is OneDNNLinear for layer in head if isinstance(layer, nn.Linear))
    # Per-agent networks run under vmap, where the layer takes torch's product: values stay those of the
    # same weights outside vmap.
    separate = make_actor_critic("mlp", hidden=32, share_params=False).critic
    shared = make_actor_critic("mlp", hidden=32, share_params=True).critic
    accelerate_cpu(separate, shared)
    shared.load_state_dict({key: value[1] for key, value in separate.state_dict().items()})
    obs = torch.randint(0, 2, (3, 2, 7, 7, 26), dtype=torch.uint8)
    td = TensorDict({("agents", "observation"): obs}, batch_size=[3])
    torch.testing.assert_close(shared(td.clone())["agents", "state_value"][:, 1],
                               separate(td.clone())["agents", "state_value"][:, 1])
