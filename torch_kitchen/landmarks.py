"""Where the nearest thing of every kind lies, seen from the observing agent: the first layer of "landmark_mlp".

The agent-centred window (`torch_kitchen.egocentric`) says what lies at each offset from the agent, but the
network still learns "a pot two steps east" and "a pot three steps east" as unrelated inputs. In a new kitchen
the pot sits at an offset it may never have met. `landmark_features` says it in a form that every kitchen
shares: for each of the observation's 26 channels, the cell nearest the agent where the channel is on (Manhattan
distance; ties to the first cell in row-major order), described by four numbers:

    present   1 if the channel is on anywhere, else 0 (and the three below are 0)
    rows      the cell's row minus the agent's, over H - 1   (negative: north)
    cols      the cell's column minus the agent's, over W - 1 (negative: west)
    value     the channel's value there, over its largest (onions in a pot over 3, cook time over 20)

What the agent holds shows on its own cell, so "nearest onion at offset (0, 0)" means "I hold an onion"; its
facing and the urgency layer read the same way. `LandmarkLinear` adds a linear map of these 104 features to the
agent-centred window's linear layer, so the encoder keeps the whole view and gains the offsets. The env's
observation stays exactly JaxMARL's: the features are computed inside the model.
"""

from __future__ import annotations

import functools

import torch
from torch import nn

from jax_env.observation import Channel
from jax_env.state import POT_FULL
from torch_kitchen.egocentric import EgocentricLinear
from torch_kitchen.onednn_linear import OneDNNLinear, plain_linear_here
from torch_kitchen.sparse_linear import nonzero_entries

FEATURES_PER_CHANNEL = 4  # present, rows, cols, value

# A channel's largest value (the others are 0 or 1): its value feature is divided by it.
CHANNEL_MAXIMA = {Channel.ONIONS_IN_POT: 3, Channel.COOKING_OR_SOUP: 3, Channel.COOK_TIME: POT_FULL}


@functools.cache
def cell_geometry(height: int, width: int, device: torch.device) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Tables indexed [agent cell, cell] (row-major), [H * W, H * W] each: the cell's rank by nearness to the
    agent (int64: Manhattan distance * H * W + cell, so ties go to the earlier cell), and its row and column
    offsets from the agent (float32, over H - 1 and W - 1)."""
    cell = torch.arange(height * width, device=device)
    rows = (cell // width)[None, :] - (cell // width)[:, None]
    cols = (cell % width)[None, :] - (cell % width)[:, None]
    rank = (rows.abs() + cols.abs()) * height * width + cell
    return rank, rows.float() / max(height - 1, 1), cols.float() / max(width - 1, 1)


@functools.cache
def value_scale(channels: int, device: torch.device) -> torch.Tensor:
    """float32 [channels]: 1 over each channel's largest value."""
    scale = torch.ones(channels, device=device)
    for channel, maximum in CHANNEL_MAXIMA.items():
        if channel < channels:
            scale[channel] = 1.0 / maximum
    return scale


def nearest_ranks(flat: torch.Tensor, agent_cell: torch.Tensor, obs_shape: tuple[int, int, int]) -> torch.Tensor:
    """int64 [N, C]: per observation and channel, the smallest `cell_geometry` rank among the cells where the
    channel is on; H * W * (H + W) (beyond every rank) where it is on nowhere. flat: [N, H * W * C]."""
    height, width, channels = obs_shape
    rank, _, _ = cell_geometry(height, width, flat.device)
    nowhere = height * width * (height + width)
    if plain_linear_here(flat, rank):  # densely: a GPU, vmap, compiled graphs
        on = flat.reshape(-1, height * width, channels) > 0
        return torch.where(on, rank[agent_cell][..., None], nowhere).amin(1)
    # On CPU from the observation's non-zero entries alone (about 2.5% of them), found once for the window layer.
    entries = nonzero_entries(flat, torch.float32)
    cell = torch.div(entries.cols, channels, rounding_mode="floor")
    channel = entries.cols - cell * channels
    nearest = torch.full((flat.shape[0] * channels,), nowhere, dtype=torch.int64, device=flat.device)
    entry_rank = rank.view(-1).take(agent_cell[entries.rows] * (height * width) + cell)
    nearest.scatter_reduce_(0, entries.rows * channels + channel, entry_rank, "amin")
    return nearest.reshape(-1, channels)


def landmark_features(obs: torch.Tensor) -> torch.Tensor:
    """uint8 (or float) observations [..., H, W, C] -> float32 [..., C * 4]: per channel, present, rows, cols,
    value of the nearest cell where it is on (see the module docstring). An observation without the agent's own
    layer reads as an agent on cell 0."""
    *batch, height, width, channels = obs.shape
    flat = obs.reshape(-1, height * width * channels)
    agent_cell = obs[..., Channel.SELF].reshape(-1, height * width).argmax(-1)  # [N]
    ranks = nearest_ranks(flat, agent_cell, (height, width, channels))
    present = ranks < height * width * (height + width)
    nearest = torch.where(present, ranks % (height * width), agent_cell[:, None])  # [N, C] cells
    _, rows, cols = cell_geometry(height, width, obs.device)
    pair = agent_cell[:, None] * (height * width) + nearest  # [N, C] into the [agent cell, cell] tables
    value = flat.gather(1, nearest * channels + torch.arange(channels, device=obs.device))
    present = present.float()
    features = torch.stack([present, rows.view(-1)[pair] * present, cols.view(-1)[pair] * present,
                            value.float() * value_scale(channels, obs.device)], dim=-1)  # [N, C, 4]
    return features.reshape(*batch, channels * FEATURES_PER_CHANNEL)


class LandmarkLinear(nn.Module):
    """The agent-centred window's linear layer plus a linear map of the landmark features: uint8 (or float)
    observations [..., H, W, C] -> float [..., out_features]. The window layer holds the bias."""

    def __init__(self, obs_shape: tuple[int, int, int], out_features: int):
        super().__init__()
        self.window = EgocentricLinear(obs_shape, out_features)
        self.landmarks = OneDNNLinear(obs_shape[-1] * FEATURES_PER_CHANNEL, out_features, bias=False)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return self.window(obs) + self.landmarks(landmark_features(obs))
