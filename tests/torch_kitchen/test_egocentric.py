import pytest
import torch
from tiny import compiled_with_operator, infinite_observations

from jax_env.observation import Channel
from torch_kitchen import egocentric
from torch_kitchen.egocentric import SparseEgocentricLinear, window_shape

SHAPE = (7, 7, 26)
HIDDEN = 16


@pytest.fixture(scope="module")
def observations() -> torch.Tensor:
    """Real Infinite Kitchen observations, uint8 [32, 2, 7, 7, 26], a few steps into their episodes."""
    return infinite_observations(32, seed=1)


def _layer() -> SparseEgocentricLinear:
    torch.manual_seed(0)
    return SparseEgocentricLinear(SHAPE, HIDDEN)


def test_the_sparse_product_equals_the_dense_window_with_gradients(observations, monkeypatch):
    layer = _layer()
    grad_out = torch.randn(32, 2, HIDDEN)
    out = layer(observations)
    out.backward(grad_out)
    grads = layer.weight.grad.clone(), layer.bias.grad.clone()
    layer.zero_grad()
    monkeypatch.setattr(egocentric, "plain_linear_here", lambda x, weight, **_: True)  # as on a GPU
    expected = layer(observations)
    expected.backward(grad_out)
    assert out.shape == (32, 2, HIDDEN)
    torch.testing.assert_close(out, expected)
    torch.testing.assert_close(grads[0], layer.weight.grad)
    torch.testing.assert_close(grads[1], layer.bias.grad)


def _kitchen(agent: tuple[int, int], pot: tuple[int, int]) -> torch.Tensor:
    obs = torch.zeros(SHAPE, dtype=torch.uint8)
    obs[agent[0], agent[1], Channel.SELF] = 1
    obs[pot[0], pot[1], Channel.POT] = 1
    return obs


def test_what_lies_beside_the_agent_meets_the_same_weights_wherever_it_stands():
    layer = _layer()
    east_of_agent = torch.stack([_kitchen((2, 3), (2, 4)), _kitchen((5, 1), (5, 2)), _kitchen((0, 5), (0, 6))])
    north_of_agent = _kitchen((3, 3), (2, 3))[None]
    out = layer(torch.cat([east_of_agent, north_of_agent]))
    torch.testing.assert_close(out[1], out[0])
    torch.testing.assert_close(out[2], out[0])
    assert not torch.allclose(out[3], out[0])


def test_the_agent_stands_at_the_windows_centre(observations):
    height, width, channels = window_shape(SHAPE)
    layer = _layer()
    with torch.no_grad():
        layer.weight.zero_()
        layer.bias.zero_()
        centre = ((height // 2) * width + width // 2) * channels + Channel.SELF
        layer.weight[0, centre] = 1.0
    torch.testing.assert_close(layer(observations)[..., 0], torch.ones(32, 2))


def test_an_all_zero_observation_gives_the_bias_and_inputs_take_no_gradient(observations):
    layer = _layer()
    torch.testing.assert_close(layer(torch.zeros(3, *SHAPE, dtype=torch.uint8)), layer.bias.detach().expand(3, -1))
    with pytest.raises(ValueError, match="no gradient"):
        layer(observations.float().requires_grad_())


def test_the_window_product_as_a_graphs_operator_is_registered_whole_and_computes_the_layers(observations):
    """`sparse_egocentric_linear`, what a compiled graph calls for the layer: torch's checks of its schema, fake
    tensor and autograd registration pass; compiled, the layer gives its eager output and gradients."""
    layer = _layer()
    flat = observations.reshape(-1, 7 * 7 * 26)
    torch.library.opcheck(egocentric.sparse_egocentric_linear, (flat, layer.weight, layer.bias, list(SHAPE)))
    grad_out = torch.randn(32, 2, HIDDEN)
    eager = layer(observations)
    eager.backward(grad_out)
    eager_grads = layer.weight.grad.clone(), layer.bias.grad.clone()
    layer.zero_grad()
    compiled = compiled_with_operator(layer, observations, "sparse_egocentric_linear", grad_out)
    torch.testing.assert_close(compiled, eager)
    torch.testing.assert_close(layer.weight.grad, eager_grads[0])
    torch.testing.assert_close(layer.bias.grad, eager_grads[1])


def test_the_actor_and_critic_reading_one_input_share_its_window_entries(observations):
    flat = observations.reshape(-1, 7 * 7 * 26)
    first = egocentric.window_entries(flat, SHAPE, torch.float32)
    assert egocentric.window_entries(flat, SHAPE, torch.float32) is first
    assert egocentric.window_entries(flat.clone(), SHAPE, torch.float32) is not first
