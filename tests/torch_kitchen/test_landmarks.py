import pytest
import torch
from tiny import infinite_observations

from jax_env.observation import Channel
from torch_kitchen import landmarks
from torch_kitchen.landmarks import FEATURES_PER_CHANNEL, LandmarkLinear, landmark_features
from torch_kitchen.models import make_actor_critic

SHAPE = (7, 7, 26)


@pytest.fixture(scope="module")
def observations() -> torch.Tensor:
    """Real Infinite Kitchen observations, uint8 [32, 2, 7, 7, 26], a few steps into their episodes."""
    return infinite_observations(32, seed=3)


def _kitchen(agent: tuple[int, int], **cells: list[tuple[int, int, int]]) -> torch.Tensor:
    """An observation with the agent at `agent` and, per channel name of `Channel`, (row, col, value) cells."""
    obs = torch.zeros(SHAPE, dtype=torch.uint8)
    obs[agent[0], agent[1], Channel.SELF] = 1
    for name, placed in cells.items():
        for row, col, value in placed:
            obs[row, col, getattr(Channel, name)] = value
    return obs


def _of(features: torch.Tensor, channel: int) -> list[float]:
    """present, rows, cols, value of one channel."""
    return features.reshape(-1, FEATURES_PER_CHANNEL)[channel].tolist()


def test_the_nearest_cell_of_each_channel_relative_to_the_agent():
    obs = _kitchen((3, 3), POT=[(0, 3, 1), (3, 6, 1)], ONIONS_IN_POT=[(3, 6, 2)], GOAL=[(6, 0, 1)])
    features = landmark_features(obs)
    assert features.shape == (26 * FEATURES_PER_CHANNEL,)
    assert _of(features, Channel.POT) == [1.0, -0.5, 0.0, 1.0]  # both pots 3 steps away: the earlier cell, north
    assert _of(features, Channel.ONIONS_IN_POT) == pytest.approx([1.0, 0.0, 0.5, 2 / 3])  # 2 of 3 onions, east
    assert _of(features, Channel.GOAL) == pytest.approx([1.0, 0.5, -0.5, 1.0])
    assert _of(features, Channel.SELF) == [1.0, 0.0, 0.0, 1.0]
    assert _of(features, Channel.PLATE_PILE) == [0.0, 0.0, 0.0, 0.0]  # none in this kitchen


def test_what_the_agent_holds_lies_on_its_own_cell():
    holding = landmark_features(_kitchen((2, 4), ONION=[(2, 4, 1), (2, 5, 1)]))
    assert _of(holding, Channel.ONION) == [1.0, 0.0, 0.0, 1.0]


def test_the_features_are_the_same_wherever_the_scene_stands():
    near = landmark_features(torch.stack([_kitchen((1, 1), POT=[(0, 2, 1)]), _kitchen((4, 4), POT=[(3, 5, 1)])]))
    torch.testing.assert_close(near[0], near[1])


def test_the_sparse_and_dense_routes_agree(observations, monkeypatch):
    sparse = landmark_features(observations)
    monkeypatch.setattr(landmarks, "plain_linear_here", lambda x, weight: True)  # as on a GPU
    assert sparse.shape == (32, 2, 26 * FEATURES_PER_CHANNEL)
    assert torch.equal(sparse, landmark_features(observations))


def test_the_layer_adds_the_landmark_map_to_the_window_layer(observations):
    torch.manual_seed(0)
    layer = LandmarkLinear(SHAPE, 8)
    expected = layer.window(observations) + landmark_features(observations) @ layer.landmarks.weight.T
    torch.testing.assert_close(layer(observations), expected)
    assert layer.landmarks.bias is None


@pytest.mark.parametrize("share_params", [True, False])
def test_landmark_mlp_acts_with_shared_and_separate_networks(observations, share_params):
    from tensordict import TensorDict

    torch.manual_seed(0)
    model = make_actor_critic("landmark_mlp", SHAPE, hidden=16, share_params=share_params)
    data = TensorDict({("agents", "observation"): observations}, [32])
    out = model.critic(model.actor(data))
    assert out["agents", "action"].shape == (32, 2)
    assert out["agents", "state_value"].shape == (32, 2, 1)
    assert torch.isfinite(out["agents", "state_value"]).all()
