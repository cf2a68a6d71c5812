"""The torch layers' JAX twins (`torch_kitchen.xla_layers`) compute what the layers compute, on real kitchens."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from torch_kitchen.egocentric import EgocentricLinear
from torch_kitchen.env import KitchenEnv
from torch_kitchen.graph import build_graph
from torch_kitchen.keys import LOGITS, OBSERVATION
from torch_kitchen.models import make_actor_critic
from torch_kitchen.models.networks import GraphEncoder
from torch_kitchen.xla_layers import agent_window, graph_scene, graph_weights

HIDDEN = 16
TOLERANCE = dict(atol=1e-5, rtol=1e-5)


@pytest.fixture(scope="module")
def observations():
    """uint8 [B, 2, H, W, C] observations of a few kitchens and random steps, by size: the Infinite Kitchen's 7x7
    and cramped room at its own 4x5."""
    torch.manual_seed(0)
    by_size = {}
    for name, levels in (("7x7", "infinite"), ("4x5", "cramped_room")):
        env = KitchenEnv(num_envs=3, levels=levels, max_steps=20, seed=1)
        with torch.no_grad():
            steps = env.rollout(6, break_when_any_done=False)
        by_size[name] = steps.get(OBSERVATION).flatten(0, 1)
    return by_size


def jax_weights(encoder: GraphEncoder) -> tuple[jax.Array, ...]:
    return tuple(jnp.asarray(weight.detach().numpy()) for weight in graph_weights(encoder))


def perturbed(encoder: GraphEncoder) -> GraphEncoder:
    """The encoder with every weight moved (the GAT bias off zero) and sharper attention scores."""
    torch.manual_seed(1)
    with torch.no_grad():
        for parameter in encoder.parameters():
            parameter.add_(0.3 * torch.randn_like(parameter))
        encoder.gat.att_src.mul_(4)
        encoder.gat.att_dst.mul_(4)
    return encoder


def agent_attention(encoder: GraphEncoder, obs: torch.Tensor) -> torch.Tensor:
    """float [N, 2, H*W + 1, heads]: torch's attention of the two agent nodes over their incoming edges."""
    graphs = obs.reshape(-1, *encoder.obs_shape).float()
    x, edge_index = build_graph(graphs)
    _, (edges, attention) = encoder.gat(x, edge_index, return_attention_weights=True)
    cells = encoder.obs_shape[0] * encoder.obs_shape[1]
    into_agents = (edges[1] % (cells + 2)) >= cells
    by_target = edges[1][into_agents].argsort(stable=True)
    return attention[into_agents][by_target].reshape(len(graphs), 2, cells + 1, -1)


@pytest.mark.parametrize("size", ["7x7", "4x5"])
@pytest.mark.parametrize("weights", ["fresh", "perturbed"])
def test_graph_scene_is_the_graph_encoder(observations, size, weights):
    obs = observations[size]
    torch.manual_seed(2)
    encoder = GraphEncoder(tuple(obs.shape[-3:]), HIDDEN)
    if weights == "perturbed":
        encoder = perturbed(encoder)
        # Sharp attention: a uniform one would hide scores summed or normalised wrongly.
        attention = agent_attention(encoder, obs)
        assert attention.max() > 5 / attention.shape[-2]
    with torch.no_grad():
        expected = encoder(obs)

    scene = jax.jit(graph_scene)(jnp.asarray(obs.numpy()), jax_weights(encoder))

    assert scene.shape == (*obs.shape[:2], HIDDEN) and scene.dtype == jnp.float32
    np.testing.assert_allclose(np.asarray(scene), expected.numpy(), **TOLERANCE)
    float_scene = graph_scene(jnp.asarray(obs.numpy(), jnp.float32), jax_weights(encoder))
    np.testing.assert_allclose(np.asarray(float_scene), expected.numpy(), **TOLERANCE)


@pytest.mark.parametrize("size", ["7x7", "4x5"])
def test_gnn_policy_runs_on_the_jax_encoder(observations, size):
    obs = observations[size]
    torch.manual_seed(3)
    actor_critic = make_actor_critic("gnn", tuple(obs.shape[-3:]), HIDDEN, True)
    encoder, head = actor_critic.acting.policy_net
    perturbed(encoder.shared_net())
    with torch.no_grad():
        logits = actor_critic.actor(TensorDict({OBSERVATION: obs}, batch_size=obs.shape[:1])).get(LOGITS)

        scene = jax.jit(graph_scene)(jnp.asarray(obs.numpy()), jax_weights(encoder.shared_net()))
        from_jax = head(torch.from_numpy(np.array(scene)))

    torch.testing.assert_close(from_jax, logits, **TOLERANCE)


@pytest.mark.parametrize("size", ["7x7", "4x5"])
def test_the_agent_window_is_the_layers_by_a_loop_over_kitchens_or_one_gather(observations, size):
    """The CPU's way (`lax.map`) and the GPU's (one gather) give `EgocentricLinear.window`'s windows exactly."""
    views = observations[size]  # [B, 2, H, W, C]
    layer = EgocentricLinear(tuple(views.shape[-3:]), HIDDEN)
    expected = layer.window(views).numpy()  # [B, 2, (2H - 1) * (2W - 1) * C]
    for one_gather in (False, True):
        windows = jax.jit(agent_window, static_argnums=1)(jnp.asarray(views.numpy()), one_gather)
        np.testing.assert_array_equal(np.asarray(windows), expected, err_msg=f"one_gather={one_gather}")
