import pytest
import torch
from tiny import infinite_observations

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
    monkeypatch.setattr(egocentric, "plain_linear_here", lambda x, weight: True)  # as on a GPU
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
