"""The models' torch layers as pure JAX functions, for rollouts inside one XLA program (`torch_kitchen.xla_rollout`).

Each function computes what its torch layer computes, on the layer's own weights (taken again at every batch), in
float32 with full-precision products, and jits with static shapes:

    dense          `nn.Linear`
    agent_window   `EgocentricLinear.window`, the agent-centred view (then `dense`)
    cell_table     the first layer over observations (`ObservationLinear` after `Flatten`, `EgocentricLinear`) as
                   a table of its products with every view a cell can give, per place (`cell_table_weights`)
    layer_norm     `nn.LayerNorm` over the last dim
    lstm_cell      one step of a one-layer `nn.LSTM`
    graph_scene    `GraphEncoder`: the kitchen graph (`torch_kitchen.graph`) -> GATConv -> ReLU -> scene linear ->
                   ReLU, its weights in `graph_weights`' order

The graph layer runs densely, with no edge list: a cell node receives its own self-loop alone, so its GAT output is
its own projection plus the bias (attention over one edge is 1); each agent node attends over the H*W cells and its
own self-loop, a softmax over H*W + 1 scores.
"""

from __future__ import annotations

from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
import torch

from jax_env.observation import CELL_VIEWS, Channel, cell_view_index
from torch_kitchen.egocentric import window_places
from torch_kitchen.models.networks import GraphEncoder

HIGHEST = jax.lax.Precision.HIGHEST  # a GPU's TF32 products would stray from torch's float32
NEGATIVE_SLOPE = 0.2  # GATConv's leaky ReLU on the attention scores, its default


def dense(x: jax.Array, weight: jax.Array, bias: jax.Array) -> jax.Array:
    """torch's `nn.Linear`: x [..., in] (cast to the weight's dtype) -> [..., out], weight [out, in], bias [out]."""
    return jnp.matmul(x.astype(weight.dtype), weight.T, precision=HIGHEST) + bias


def agent_window(obs: jax.Array) -> jax.Array:
    """`EgocentricLinear.window` in JAX: observations [..., H, W, C] -> their agent-centred windows [..., (2H - 1) *
    (2W - 1) * C], flat, as one gather of every view's window out of the kitchen padded by H - 1 rows and W - 1
    columns of zeros on every side (a GPU's way: on a CPU the layer reads a cell table, `cell_table`)."""
    *batch, height, width, channels = obs.shape
    flat = obs.reshape(-1, height, width, channels)
    agent_cell = flat[..., Channel.SELF].reshape(len(flat), -1).argmax(-1)  # an all-zero row: cell 0, as torch's
    padded = jnp.pad(flat, ((0, 0), (height - 1, height - 1), (width - 1, width - 1), (0, 0)))
    rows = (agent_cell // width)[:, None] + jnp.arange(2 * height - 1)  # [K, 2H - 1]
    columns = (agent_cell % width)[:, None] + jnp.arange(2 * width - 1)  # [K, 2W - 1]
    kitchens = jnp.arange(len(flat))[:, None, None]
    return padded[kitchens, rows[:, :, None], columns[:, None, :]].reshape(*batch, -1)


def cell_offsets(obs_shape: tuple[int, int, int], agent_centred: bool) -> np.ndarray:
    """int32 [A, H * W]: where each cell of the kitchen lands among the first layer's places with the agent on cell a:
    its place in the agent-centred window (`window_places`, A = H * W agent cells), or the cell itself (A = 1)."""
    if agent_centred:
        return window_places(obs_shape).numpy().astype(np.int32)
    return np.arange(obs_shape[0] * obs_shape[1], dtype=np.int32)[None]


def _view_entries() -> tuple[np.ndarray, np.ndarray]:
    """`CELL_VIEWS` by their set channels: (channel int [K, D], value uint8 [K, D]), the k-th set channel of each view
    (a view with fewer reads channel 0 at value 0)."""
    count = int((CELL_VIEWS != 0).sum(-1).max())
    channels = np.zeros((count, len(CELL_VIEWS)), np.int64)
    values = np.zeros((count, len(CELL_VIEWS)), np.uint8)
    for view, row in enumerate(CELL_VIEWS):
        (set_channels,) = row.nonzero()
        channels[:len(set_channels), view], values[:len(set_channels), view] = set_channels, row[set_channels]
    return channels, values


VIEW_ENTRIES = _view_entries()


def cell_table_weights(weight: jax.Array, obs_shape: tuple[int, int, int], agent_centred: bool
                       ) -> tuple[jax.Array, jax.Array]:
    """A first layer's weight [out, places * C] over observations [..., H, W, C] as `cell_table` reads it: (the
    products of the weight at each place with each of the `CELL_VIEWS` [places * D, out], the urgency layer's
    product over the whole kitchen for each agent cell [A, out]). Made once per batch of steps: a step then sums one
    row per cell, not a product over the (mostly zero) inputs."""
    out_features = weight.shape[0]
    channels = obs_shape[-1]
    per_place = weight.reshape(out_features, -1, channels).transpose(1, 2, 0)  # [places, C, out]
    table = jnp.zeros((per_place.shape[0], len(CELL_VIEWS), out_features), weight.dtype)
    for channel, value in zip(*VIEW_ENTRIES):  # each view's channels one after another: sums in a fixed order
        table = table + jnp.asarray(value, weight.dtype)[:, None] * per_place[:, channel]
    urgency = _in_order(per_place[cell_offsets(obs_shape, agent_centred), Channel.URGENCY])
    return table.reshape(-1, out_features), urgency


def _in_order(rows: jax.Array) -> jax.Array:
    """rows [N, K, out] summed over K one row after another: the same bits whatever the batch around it (a reduction
    may be split otherwise for another shape, as for teams stacked by vmap and a team alone)."""
    total = rows[:, 0]
    for index in range(1, rows.shape[1]):
        total = total + rows[:, index]
    return total


def cell_table(obs: jax.Array, table: jax.Array, urgency: jax.Array, bias: jax.Array, agent_centred: bool
               ) -> jax.Array:
    """The first layer (`cell_table_weights`' table and urgency, and its bias) on observations [..., H, W, C]
    -> [..., out]: per cell, the table's row for its place and its view; the urgency layer's row where it is on."""
    *batch, height, width, channels = obs.shape
    flat = obs.reshape(-1, height * width, channels)
    agent_cell = flat[..., Channel.SELF].argmax(-1) if agent_centred else jnp.zeros(len(flat), jnp.int32)
    places = jnp.asarray(cell_offsets((height, width, channels), agent_centred))[agent_cell]  # [N, H * W]
    rows = places * len(CELL_VIEWS) + cell_view_index(flat)
    summed = _in_order(table[rows]) + flat[:, 0, Channel.URGENCY, None].astype(table.dtype) * urgency[agent_cell]
    return (summed + bias).reshape(*batch, -1)


def layer_norm(x: jax.Array, weight: jax.Array, bias: jax.Array, eps: float) -> jax.Array:
    """torch's `nn.LayerNorm` over the last dim: the biased variance, eps inside the square root."""
    mean = x.mean(-1, keepdims=True)
    variance = jnp.square(x - mean).mean(-1, keepdims=True)
    return (x - mean) * jax.lax.rsqrt(variance + eps) * weight + bias


def lstm_cell(weights: Sequence[jax.Array], x: jax.Array, state: tuple[jax.Array, jax.Array]
              ) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
    """One step of torch's one-layer `nn.LSTM` (gates i, f, g, o): x [..., in] and the state (h, c) [..., 1, hidden]
    as the env carries them -> (h [..., hidden], the next state (h, c) [..., 1, hidden])."""
    weight_ih, weight_hh, bias_ih, bias_hh = weights
    hidden, cell = (value[..., 0, :] for value in state)
    gates = dense(x, weight_ih, bias_ih) + dense(hidden, weight_hh, bias_hh)
    in_gate, forget_gate, cell_gate, out_gate = jnp.split(gates, 4, axis=-1)
    cell = jax.nn.sigmoid(forget_gate) * cell + jax.nn.sigmoid(in_gate) * jnp.tanh(cell_gate)
    hidden = jax.nn.sigmoid(out_gate) * jnp.tanh(cell)
    return hidden, (hidden[..., None, :], cell[..., None, :])


def graph_runs(encoder: GraphEncoder) -> bool:
    """Whether `graph_scene` computes this encoder's GATConv: one shared projection, concatenated heads, a bias,
    GATConv's slope, no residual, no edge features (as `GraphEncoder` builds it)."""
    gat = encoder.gat
    return (gat.lin is not None and gat.res is None and gat.lin_edge is None and gat.bias is not None and gat.concat
            and gat.negative_slope == NEGATIVE_SLOPE)


def graph_weights(encoder: GraphEncoder) -> tuple[torch.Tensor, ...]:
    """A `GraphEncoder`'s parameters in the order `graph_scene` reads them: the GAT layer's projection weight
    [heads * F, C] (bias-free), att_src and att_dst [1, heads, F], its bias [heads * F], the scene layer's weight
    [hidden, (H*W + 2) * heads * F] and bias [hidden]. ValueError unless `graph_runs(encoder)`."""
    if not graph_runs(encoder):
        raise ValueError(f"graph_scene runs GraphEncoder's own GATConv: one shared projection, concatenated heads, a "
                         f"bias, negative_slope {NEGATIVE_SLOPE}, no residual, no edge features")
    gat = encoder.gat
    return gat.lin.weight, gat.att_src, gat.att_dst, gat.bias, encoder.scene.weight, encoder.scene.bias


def graph_attention(projected: jax.Array, agent_cells: jax.Array, att_src: jax.Array, att_dst: jax.Array
                    ) -> jax.Array:
    """GATConv's messages into the two agent nodes: each agent node attends over every cell and its own self-loop.

    projected: float32 [..., H*W, heads, F], the cells' projections (an agent node's is its cell's, since its
    features are its cell's channels). agent_cells: int [..., 2], the cell of the observing agent and of its
    partner. att_src, att_dst: [1, heads, F]. -> float32 [..., 2, heads, F], before GATConv's bias.
    """
    agents = jnp.take_along_axis(projected, agent_cells[..., None, None], axis=-3)  # [..., 2, heads, F]
    source_scores = (projected * att_src[0]).sum(-1)  # [..., H*W, heads]
    agent_source_scores = (agents * att_src[0]).sum(-1)  # [..., 2, heads]
    target_scores = (agents * att_dst[0]).sum(-1)  # [..., 2, heads]
    # Edge (source j -> target i) scores a_src.x_j + a_dst.x_i, over the H*W cells then the self-loop.
    cell_scores = source_scores[..., None, :, :] + target_scores[..., :, None, :]  # [..., 2, H*W, heads]
    self_scores = agent_source_scores + target_scores  # [..., 2, heads]
    scores = jnp.concatenate([cell_scores, self_scores[..., None, :]], axis=-2)
    attention = jax.nn.softmax(jax.nn.leaky_relu(scores, NEGATIVE_SLOPE), axis=-2)  # [..., 2, H*W + 1, heads]
    from_cells = jnp.einsum("...ash,...shf->...ahf", attention[..., :-1, :], projected, precision=HIGHEST)
    return from_cells + attention[..., -1, :, None] * agents


def graph_scene(obs: jax.Array, weights: tuple[jax.Array, ...]) -> jax.Array:
    """`GraphEncoder.forward` in JAX: observations uint8 or float [..., H, W, C] -> float32 [..., hidden].

    weights: `graph_weights(encoder)` as JAX arrays. The nodes are flattened in torch's order (`torch_kitchen.graph`):
    the H*W cells row by row, the observing agent, its partner; each node's heads concatenated.
    """
    lin_weight, att_src, att_dst, gat_bias, scene_weight, scene_bias = weights
    *batch, height, width, channels = obs.shape
    heads, features = att_src.shape[-2:]
    cells = obs.astype(jnp.float32).reshape(*batch, height * width, channels)
    # An agent stands on the cell where its channel (0: the observing agent, 1: its partner) is 1; an agent off the
    # grid reads cell 0, as torch's argmax does.
    agent_cells = cells[..., :2].argmax(axis=-2)  # [..., 2]
    projected = jnp.matmul(cells, lin_weight.T, precision=HIGHEST).reshape(*batch, height * width, heads, features)
    agents = graph_attention(projected, agent_cells, att_src, att_dst)
    nodes = jnp.concatenate([projected, agents], axis=-3).reshape(*batch, height * width + 2, heads * features)
    nodes = jax.nn.relu(nodes + gat_bias)
    return jax.nn.relu(dense(nodes.reshape(*batch, -1), scene_weight, scene_bias))
