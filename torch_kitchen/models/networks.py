"""A network of the kitchens' models: an encoder (MLP, agent-centred MLP or GNN), a head, one network per
agent or one shared (`ObservationEncoder`, TorchRL's `MultiAgentNetBase`), and `make_network`, a torso and head
as a TensorDict module, with an LSTM for the recurrent variants. Orthogonal init as in the authors' code.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import torch
from tensordict.nn import (
    TensorDictModule,
    TensorDictSequential,
)
from torch import nn
from torch_geometric.nn import GATConv

from torch_kitchen.egocentric import EgocentricLinear
from torch_kitchen.graph import build_graph, num_nodes
from torch_kitchen.keys import (
    OBSERVATION,
)
from torch_kitchen.models.recurrence import MultiAgentLSTM
from torch_kitchen.sparse_linear import ObservationLinear
from torch_kitchen.torchrl_internals import MultiAgentNet

GAT_HEADS, GAT_FEATURES = 4, 8  # per head; concatenated -> 32 features per node


def _orthogonal_(layer: nn.Linear, gain: float) -> nn.Linear:
    nn.init.orthogonal_(layer.weight, gain)
    nn.init.zeros_(layer.bias)
    return layer


def _hidden_linear(in_features: int, out_features: int, layer: type[nn.Linear] = nn.Linear) -> nn.Linear:
    return _orthogonal_(layer(in_features, out_features), math.sqrt(2))


class GraphEncoder(nn.Module):
    """Kitchen graph -> one GAT layer -> scene embedding: [..., H, W, C] (uint8 or float) -> float [..., hidden]."""

    def __init__(self, obs_shape: tuple[int, int, int], hidden: int):
        super().__init__()
        height, width, channels = obs_shape
        self.obs_shape = tuple(obs_shape)
        # Self-loops are part of the graph's edge list (torch_kitchen.graph): don't let GATConv rebuild them.
        self.gat = GATConv(channels, GAT_FEATURES, heads=GAT_HEADS, add_self_loops=False)
        self.scene = _hidden_linear(num_nodes(height, width) * GAT_HEADS * GAT_FEATURES, hidden)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        batch = obs.shape[:-3]
        graphs = obs.reshape(-1, *self.obs_shape).to(torch.float32)
        x, edge_index = build_graph(graphs)
        nodes = torch.relu(self.gat(x, edge_index))  # [N * (H*W + 2), 32]
        scene = torch.relu(self.scene(nodes.reshape(graphs.shape[0], -1)))
        return scene.reshape(*batch, -1)


def make_encoder(kind: str, obs_shape: tuple[int, int, int], hidden: int) -> nn.Module:
    """One agent's encoder: [..., H, W, C] (uint8 observations or float) -> float [..., hidden]; kind "mlp",
    "ego_mlp" (agent-centred) or "gnn". The MLPs' first layer reads uint8 observations (`ObservationLinear`,
    `EgocentricLinear`); on a CPU, `accelerate_cpu` makes it read their non-zero entries alone."""
    if kind == "mlp":
        return nn.Sequential(nn.Flatten(-3), _hidden_linear(math.prod(obs_shape), hidden, ObservationLinear), nn.ReLU())
    if kind == "ego_mlp":
        return nn.Sequential(_orthogonal_(EgocentricLinear(obs_shape, hidden), math.sqrt(2)), nn.ReLU())
    if kind == "gnn":
        return GraphEncoder(obs_shape, hidden)
    raise ValueError(f"unknown encoder {kind!r}, expected 'mlp', 'ego_mlp' or 'gnn'")


def make_head(hidden: int, out_features: int, out_gain: float, layer_norm: bool, in_features: int | None = None
              ) -> nn.Sequential:
    """One agent's head: float [..., in_features] -> float [..., out_features], after a LayerNorm if `layer_norm`.

    in_features: `hidden` by default; wider when other inputs (E3T's partner prediction) join the torso's output.
    """
    in_features = in_features or hidden
    layers = [nn.LayerNorm(in_features)] if layer_norm else []
    layers += [_hidden_linear(in_features, hidden), nn.ReLU(), _hidden_linear(hidden, hidden), nn.ReLU()]
    layers.append(_orthogonal_(nn.Linear(hidden, out_features), out_gain))
    return nn.Sequential(*layers)


class ObservationEncoder(MultiAgentNet):
    """Both agents' observations, uint8 [..., 2, H, W, C], to embeddings float32 [..., 2, hidden]. The encoders
    read the uint8 values themselves (the MLP's sparse first layer finds the non-zero bytes without a cast)."""

    def __init__(self, kind: str, obs_shape: tuple[int, int, int], hidden: int, share_params: bool = True):
        super().__init__(functools.partial(make_encoder, kind, obs_shape, hidden), obs_shape,
                         share_params=share_params)

    def check_input(self, inputs: torch.Tensor) -> torch.Tensor:
        height, width, channels = self.in_shape
        if tuple(inputs.shape[-4:]) != (self.n_agents, *self.in_shape):
            raise ValueError(
                f"observation of shape {list(inputs.shape)}, but this model was built for [..., {self.n_agents}, "
                f"{height}, {width}, {channels}] (obs_shape={self.in_shape}): a model built for {height}x{width} "
                f"kitchens needs {height}x{width} levels (7x7: the Infinite Kitchen and the expanded classic "
                f"layouts), or build it with make_actor_critic(..., obs_shape={tuple(inputs.shape[-3:])})"
            )
        return inputs


def make_network(
    net: str,
    encoder: str,
    out_key: tuple[str, str],
    out_features: int,
    out_gain: float,
    obs_shape: tuple[int, int, int],
    hidden: int,
    recurrent: bool,
    share_params: bool,
    extra_inputs: Sequence[tuple[tuple[str, str], int]] = (),
) -> TensorDictSequential:
    """One torso + head as a TensorDictSequential: ("agents", "observation") -> `out_key` [*B, 2, out_features].

    extra_inputs: (key, width) of per-agent features [*B, 2, width] concatenated to the torso's output before
    the head (E3T's partner prediction). Intermediate keys ("agents", "<net>_embedding" | "<net>_memory") are
    dropped from the output, so rollouts don't store them.
    """
    embedding, memory = ("agents", f"{net}_embedding"), ("agents", f"{net}_memory")
    modules = [
        TensorDictModule(ObservationEncoder(encoder, obs_shape, hidden, share_params),
                         in_keys=[OBSERVATION], out_keys=[embedding])
    ]
    selected = [out_key]
    if recurrent:
        lstm = MultiAgentLSTM(net, hidden, share_params)
        modules.append(lstm)
        selected += lstm.out_keys[1:]
    in_features = hidden + sum(width for _, width in extra_inputs)
    head = MultiAgentNet(functools.partial(make_head, hidden, out_features, out_gain, recurrent, in_features),
                         (in_features,), share_params=share_params)
    head_inputs = [memory if recurrent else embedding, *(key for key, _ in extra_inputs)]
    modules.append(TensorDictModule(head, in_keys=head_inputs, out_keys=[out_key]))
    return TensorDictSequential(*modules, selected_out_keys=selected)
