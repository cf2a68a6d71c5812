"""The torch layers' JAX twins (`torch_kitchen.xla_layers`) compute what the layers compute, on real kitchens."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import torch
from tensordict import TensorDict

from jax_env.observation import CELL_VIEWS, Channel, cell_view_index
from torch_kitchen.egocentric import EgocentricLinear
from torch_kitchen.env import KitchenEnv
from torch_kitchen.graph import build_graph
from torch_kitchen.keys import LOGITS, OBSERVATION
from torch_kitchen.models import make_actor_critic
from torch_kitchen.models.networks import GraphEncoder
from torch_kitchen.partners.scripted_cook import ScriptedCook
from torch_kitchen.xla_layers import agent_window, cell_table, cell_table_weights, dense, graph_scene, graph_weights

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
def test_the_agent_window_is_the_layers(observations, size):
    """One gather gives `EgocentricLinear.window`'s windows exactly."""
    views = observations[size]  # [B, 2, H, W, C]
    layer = EgocentricLinear(tuple(views.shape[-3:]), HIDDEN)
    windows = jax.jit(agent_window)(jnp.asarray(views.numpy()))
    np.testing.assert_array_equal(np.asarray(windows), layer.window(views).numpy())


@pytest.fixture(scope="module")
def cooked():
    """uint8 [N, 2, H, W, C] views of two scripted cooks at work for 90 steps of 100-step episodes (pots filling,
    cooking and ready, soups carried and delivered, the urgency layer on for the last 40) on the expanded classic
    layouts and generated levels."""
    cook, by_levels = ScriptedCook(), []
    for levels in (["cramped_room_7x7", "coord_ring_7x7", "counter_circuit_7x7"], "infinite"):
        env = KitchenEnv(num_envs=3, levels=levels, max_steps=100, seed=2)
        tensordict, views = env.reset(), []
        for _ in range(90):
            views.append(tensordict[OBSERVATION].clone())
            tensordict["agents", "action"] = cook(tensordict[OBSERVATION]).argmax(-1)
            tensordict = env.step(tensordict)["next"]
        by_levels.append(torch.cat(views))
    return torch.cat(by_levels).numpy()


def test_every_cell_of_a_view_is_one_of_the_cell_views(cooked):
    """The cell table's premise: a cell's channels, bar urgency, are one of `CELL_VIEWS`, found by its index."""
    for channel in (Channel.COOK_TIME, Channel.SOUP, Channel.URGENCY):  # the views hold every state they should
        assert cooked[..., channel].any() and not cooked[..., channel].all(), channel
    without_urgency = cooked.copy()
    without_urgency[..., Channel.URGENCY] = 0
    found = CELL_VIEWS[np.asarray(jax.jit(cell_view_index)(jnp.asarray(cooked)))]
    np.testing.assert_array_equal(found, without_urgency)
    assert len({tuple(row) for row in CELL_VIEWS}) == len(CELL_VIEWS)


@pytest.mark.parametrize("agent_centred", [True, False], ids=["agent-centred", "flat"])
def test_the_cell_table_is_the_first_layers_product(cooked, agent_centred):
    """The first layer from its cell table gives the dense product over the agent-centred window (or the flattened
    view), with and without urgency, to float rounding."""
    views = jnp.asarray(cooked)
    obs_shape = tuple(views.shape[-3:])
    inputs = agent_window(views) if agent_centred else views.reshape(*views.shape[:-3], -1)
    generator = np.random.default_rng(0)
    weight = jnp.asarray(generator.normal(0, 0.1, (HIDDEN, inputs.shape[-1])), jnp.float32)
    bias = jnp.asarray(generator.normal(0, 0.1, HIDDEN), jnp.float32)
    table, urgency = cell_table_weights(weight, obs_shape, agent_centred)
    tabled = jax.jit(cell_table, static_argnums=4)(views, table, urgency, bias, agent_centred)
    np.testing.assert_allclose(np.asarray(tabled), np.asarray(dense(inputs, weight, bias)), **TOLERANCE)
