"""The kitchen as the observing agent sees it: an agent-centred first layer for the MLP ("ego_mlp").

The observation shows the whole kitchen at fixed positions, so an MLP over it must learn what "the pot to my
left" means separately for every cell the agent may stand on, and again in every new layout. `EgocentricLinear`
moves the observation [H, W, C] into a window of (2H - 1) x (2W - 1) cells centred on the agent (channel 0 marks
where it stands; cells beyond the kitchen are zero), then applies a linear layer to the window: what lies one step
north of the agent always meets the same weights. The env's observation stays exactly JaxMARL's; the move is
part of the model.

`EgocentricLinear` builds the window densely by a scatter. On a CPU the move costs almost nothing:
`SparseEgocentricLinear` (made by `torch_kitchen.cpu_kernels.accelerate_cpu`) finds the observation's non-zero
entries (as `SparseInputLinear` does) and only renumbers their columns; both give the same products (tested).
"""

from __future__ import annotations

import functools

import torch
from torch import nn
from torch.nn import functional as F

from jax_env.observation import Channel
from torch_kitchen.onednn_linear import plain_linear_here
from torch_kitchen.sparse_linear import (
    NonZeroEntries,
    SparseProduct,
    nonzero_entries,
    sparse_product,
    store_by_column,
)


def window_shape(obs_shape: tuple[int, int, int]) -> tuple[int, int, int]:
    """(2H - 1, 2W - 1, C): every cell of an H x W kitchen stays inside the window wherever the agent stands."""
    height, width, channels = obs_shape
    return 2 * height - 1, 2 * width - 1, channels


def window_places(obs_shape: tuple[int, int, int]) -> torch.Tensor:
    """int64 [H * W, H * W]: for the agent on cell s (row-major), the place of each cell among the window's
    (2H - 1) x (2W - 1) cells, row-major."""
    height, width, _ = obs_shape
    _, window_width, _ = window_shape(obs_shape)
    cell = torch.arange(height * width)
    agent = cell[:, None]
    row = cell // width - agent // width + height - 1
    col = cell % width - agent % width + width - 1
    return row * window_width + col


@functools.cache
def window_columns(obs_shape: tuple[int, int, int], device: torch.device) -> torch.Tensor:
    """int64 [H * W, H * W * C] on `device`: for the agent on cell s (row-major), where the observation's flat
    column j (cell, channel) lands in the flat window."""
    channels = obs_shape[-1]
    columns = window_places(obs_shape)[:, :, None] * channels + torch.arange(channels)
    return columns.reshape(len(columns), -1).to(device)


class EgocentricLinear(nn.Linear):
    """A linear layer over the agent-centred window of an observation (see the module docstring).

    uint8 (or float) observations [..., H, W, C] -> float [..., out_features]; the weight is [out, (2H - 1) *
    (2W - 1) * C]. The window is built densely by a scatter; on a CPU, `accelerate_cpu` makes the layer a
    `SparseEgocentricLinear`.
    """

    def __init__(self, obs_shape: tuple[int, int, int], out_features: int, device=None, dtype=None):
        super().__init__(torch.Size(window_shape(obs_shape)).numel(), out_features, device=device, dtype=dtype)
        self.obs_shape = tuple(obs_shape)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        return F.linear(self.window(obs), self.weight, self.bias)

    def window(self, obs: torch.Tensor) -> torch.Tensor:
        """The agent-centred window of observations [..., H, W, C] as the layer's dense input float [..., in]."""
        height, width, channels = self.obs_shape
        flat = obs.reshape(-1, height * width * channels)
        agent_cell = obs[..., Channel.SELF].reshape(-1, height * width).argmax(-1)  # an all-zero row: cell 0
        columns = window_columns(self.obs_shape, flat.device)
        window = torch.zeros(flat.shape[0], self.in_features, dtype=self.weight.dtype, device=flat.device)
        window = window.scatter(1, columns[agent_cell], flat.to(self.weight.dtype))
        return window.reshape(*obs.shape[:-3], self.in_features)


class SparseEgocentricLinear(EgocentricLinear):
    """`EgocentricLinear` from the observation's non-zero entries, their columns renumbered into the window (see
    the module docstring); made by `torch_kitchen.cpu_kernels.accelerate_cpu`. The observation takes no gradient
    (none is asked of observations)."""

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        store_by_column(self.weight)

    def forward(self, obs: torch.Tensor) -> torch.Tensor:
        if obs.requires_grad:
            raise ValueError("EgocentricLinear takes no gradient for its input: pass observations, not features")
        flat = obs.reshape(-1, torch.Size(self.obs_shape).numel())
        if plain_linear_here(flat, self.weight, in_graph=True):
            return super().forward(obs)
        if torch.compiler.is_compiling():  # the product as one operator of the graph
            out = sparse_egocentric_linear(flat, self.weight, self.bias, list(self.obs_shape))
        else:
            entries = window_entries(flat, self.obs_shape, self.weight.dtype)
            out = SparseProduct.apply(flat, self.weight, self.bias, entries)
        return out.reshape(*obs.shape[:-3], self.out_features)


def window_entries(flat: torch.Tensor, obs_shape: tuple[int, int, int], dtype: torch.dtype) -> NonZeroEntries:
    """The non-zero entries of observations flat [N, H * W * C] with their columns renumbered into each row's
    agent-centred window, made once per input (`NonZeroEntries.derived`)."""
    entries = nonzero_entries(flat, dtype)

    def moved() -> NonZeroEntries:
        height, width, channels = obs_shape
        agent_cell = flat.reshape(-1, height * width, channels)[..., Channel.SELF].argmax(-1)  # all-zero row: cell 0
        columns = window_columns(tuple(obs_shape), flat.device)
        cols = columns.reshape(-1).take(agent_cell[entries.rows] * flat.shape[1] + entries.cols)
        return entries.moved(cols, torch.Size(window_shape(obs_shape)).numel())

    return entries.derived(("window", tuple(obs_shape)), moved)


@torch.library.custom_op("kitchen::sparse_egocentric_linear", mutates_args=())
def sparse_egocentric_linear(flat: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, obs_shape: list[int]
                             ) -> torch.Tensor:
    """`SparseEgocentricLinear`'s product as one operator that a compiled graph calls as it is (as
    `torch_kitchen.sparse_linear.sparse_input_linear`): observations flat [N, H * W * C] -> float [N, out]."""
    return sparse_product(window_entries(flat, tuple(obs_shape), weight.dtype), weight, bias)


@sparse_egocentric_linear.register_fake
def _(flat: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, obs_shape: list[int]) -> torch.Tensor:
    return weight.new_empty((flat.shape[0], weight.shape[0]))


@torch.library.custom_op("kitchen::sparse_egocentric_weight_gradient", mutates_args=())
def sparse_egocentric_weight_gradient(flat: torch.Tensor, grad_out: torch.Tensor, obs_shape: list[int]
                                      ) -> torch.Tensor:
    """window.T @ grad_out [window, out], from the observations' `window_entries`."""
    return window_entries(flat, tuple(obs_shape), grad_out.dtype).weight_gradient(grad_out)


@sparse_egocentric_weight_gradient.register_fake
def _(flat: torch.Tensor, grad_out: torch.Tensor, obs_shape: list[int]) -> torch.Tensor:
    return grad_out.new_empty((torch.Size(window_shape(obs_shape)).numel(), grad_out.shape[1]))


def _save_observations(ctx, inputs, output) -> None:
    ctx.save_for_backward(inputs[0])
    ctx.obs_shape = inputs[3]


def _sparse_egocentric_backward(ctx, grad_out: torch.Tensor):
    (flat,) = ctx.saved_tensors
    return None, sparse_egocentric_weight_gradient(flat, grad_out, ctx.obs_shape).t(), grad_out.sum(0), None


sparse_egocentric_linear.register_autograd(_sparse_egocentric_backward, setup_context=_save_observations)
