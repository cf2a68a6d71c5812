"""The kitchen as a graph for the GNN models: grid cells and the two agents as nodes.

The paper says only that "every grid cell is a node whose features are its 26 channels; every cell node is
connected to the agents' nodes, plus self-loops"; the authors' code was never published. Our design:

Nodes of one graph (n = H*W + 2):
    0 .. H*W-1   the cells, node y*W + x for cell (y, x), features = the cell's 26 channels.
    H*W          the observing agent (located by channel 0, "self here"),
    H*W + 1      its partner (channel 1, "other here");
                 an agent node's features are the 26 channels of the cell it stands on, so the attention of the
                 agent nodes is queried from what the agent sees under its feet (position, facing, held item).
Edges (directed, source -> target, message passing runs along them):
    every cell -> the observing agent's node (H*W edges, in cell order), then
    every cell -> the partner's node (H*W edges, in cell order), then
    a self-loop on every node (n edges, in node order),
    E = 3*H*W + 2 edges in all. The self-loops are explicit, so the GAT layer is built with
    `add_self_loops=False` and does not rebuild them on every call. A cell node receives only its own
    self-loop: with one GAT layer, the cells keep (a projection of) their own features and the agent nodes
    attend over the whole grid.

The edge list is the same for every observation; N graphs are batched as one disjoint graph by offsetting
graph k's node indices by k*n (`batched_edges`, cached per (H, W, N, device)), with no per-sample Python.
"""

from __future__ import annotations

import functools

import torch


def num_nodes(height: int, width: int) -> int:
    """Nodes of one kitchen graph: the H*W cells and the two agents."""
    return height * width + 2


def graph_edges(height: int, width: int) -> torch.Tensor:
    """int64 [2, 3*H*W + 2]: (source, target) of one graph's edges, in the order of the module docstring."""
    cells = height * width
    cell_ids = torch.arange(cells)
    nodes = torch.arange(num_nodes(height, width))
    sources = torch.cat([cell_ids, cell_ids, nodes])
    targets = torch.cat([torch.full((cells,), cells), torch.full((cells,), cells + 1), nodes])
    return torch.stack([sources, targets])


@functools.lru_cache(maxsize=64)
def batched_edges(height: int, width: int, num_graphs: int, device: torch.device) -> torch.Tensor:
    """int64 [2, N*E]: the edges of N disjoint kitchen graphs, graph k's nodes offset by k*(H*W + 2).

    Cached: a rollout or a minibatch asks for the same N over and over. Built outside inference mode, so a
    cache filled during evaluation (inference tensors) can still index a graph that autograd records.
    """
    with torch.inference_mode(False):
        edges = graph_edges(height, width).to(device)
        offsets = torch.arange(num_graphs, device=device) * num_nodes(height, width)
        return (edges.unsqueeze(1) + offsets.view(1, -1, 1)).reshape(2, -1)


def node_features(obs: torch.Tensor) -> torch.Tensor:
    """float [N, H*W + 2, C]: cell features then the two agents' cells (see the module docstring).

    obs: float [N, H, W, C], channel 0 marks the observing agent's cell and channel 1 the partner's. An agent
    that is not on the grid (no 1 in its channel) would read cell 0: the kitchens always place both.
    """
    num_graphs, height, width, channels = obs.shape
    cells = obs.reshape(num_graphs, height * width, channels)
    # argmax over the cells of channels 0 and 1: the two agents' cell indices, [N, 2].
    agent_cells = cells[..., :2].argmax(dim=1)
    agents = torch.gather(cells, 1, agent_cells.unsqueeze(-1).expand(-1, -1, channels))
    return torch.cat([cells, agents], dim=1)


def build_graph(obs: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """N kitchen graphs batched as one disjoint graph, in torch-geometric's layout.

    obs: float [N, H, W, C]. Returns x float [N*(H*W + 2), C] (graph k's nodes at rows k*n .. k*n + n-1) and
    edge_index int64 [2, N*(3*H*W + 2)] (self-loops included).
    """
    num_graphs, height, width, channels = obs.shape
    x = node_features(obs).reshape(-1, channels)
    return x, batched_edges(height, width, num_graphs, obs.device)
