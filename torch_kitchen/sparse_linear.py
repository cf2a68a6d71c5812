"""A linear layer for mostly-zero inputs: the MLP encoders' first layer.

A kitchen's observation is about 2.5% non-zero (the Infinite Kitchen: some 32 of 7 x 7 x 26 = 1,274 inputs per
agent), and the first layer over it holds most of an MLP's arithmetic: at hidden 256 its forward and weight
gradient are three quarters of a PPO minibatch on a CPU. `SparseInputLinear` computes the same product from the
non-zero entries alone, in both directions, as CSR matrix products. It is `nn.Linear` in every other respect
(same parameters, state_dict keys and init), so checkpoints and user code see no difference; the sums run in
another order, so results agree with `nn.Linear` to float32 rounding, not bit for bit.

Where finding the non-zeros would cost more than it saves, the layer is a plain `nn.Linear`: on a GPU (whose
`nonzero` waits for the device, and whose dense products are cheap), and inside `torch.compile`'s graphs.
"""

from __future__ import annotations

import warnings

import torch
from torch import nn
from torch.nn import functional as F

# Only the CSR constructor's notice that its API is in beta: the products used here are CPU kernels of long standing.
warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta", category=UserWarning)


def _csr(rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """The CSR matrix of `shape` with `values` at (`rows`, `cols`); the entries sorted by row, then column."""
    crow = torch.zeros(shape[0] + 1, dtype=torch.int64)
    torch.cumsum(torch.bincount(rows, minlength=shape[0]), 0, out=crow[1:])
    return torch.sparse_csr_tensor(crow, cols, values, shape, check_invariants=False)  # valid by construction


class SparseProduct(torch.autograd.Function):
    """x @ weight.T + bias from x's non-zero entries: x [N, in] (any real dtype; uint8 observations are read as
    they are), weight float [out, in], bias [out] -> float [N, out]."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
        rows, cols = x.nonzero(as_tuple=True)  # row-major: sorted by row, then column
        values = x[rows, cols].to(weight.dtype)
        ctx.save_for_backward(weight, rows, cols, values)
        ctx.in_shape = tuple(x.shape)
        return torch.addmm(bias, _csr(rows, cols, values, ctx.in_shape), weight.t())

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        weight, rows, cols, values = ctx.saved_tensors
        grad_x = grad_weight = grad_bias = None
        if ctx.needs_input_grad[0]:  # observations never need it; other inputs might
            grad_x = grad_out @ weight
        if ctx.needs_input_grad[1]:
            # weight's gradient grad_out.T @ x, as (x.T @ grad_out).T with x.T in CSR: x's entries by column.
            by_col = torch.argsort(cols, stable=True)
            x_t = _csr(cols[by_col], rows[by_col], values[by_col], ctx.in_shape[::-1])
            grad_weight = torch.sparse.mm(x_t, grad_out).t()
        if ctx.needs_input_grad[2]:
            grad_bias = grad_out.sum(0)
        return grad_x, grad_weight, grad_bias


def _under_vmap(x: torch.Tensor) -> bool:
    """Whether `x` is a slice of a vmapped batch (separate networks per agent run under TorchRL's vmap)."""
    return torch._C._functorch.is_batchedtensor(x)


class SparseInputLinear(nn.Linear):
    """`nn.Linear` computed from the non-zero entries of its input, on CPU (see the module docstring).

    [..., in_features] of any real dtype (uint8 observations need no cast) -> float [..., out_features]; a layer
    with a bias.
    """

    def __init__(self, in_features: int, out_features: int, device=None, dtype=None):
        super().__init__(in_features, out_features, bias=True, device=device, dtype=dtype)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # `nonzero` has no batched form under vmap and would stop torch.compile's graph.
        if x.device.type != "cpu" or torch.compiler.is_compiling() or _under_vmap(x) or _under_vmap(self.weight):
            return F.linear(x.to(self.weight.dtype), self.weight, self.bias)
        flat = x.reshape(-1, self.in_features)
        out = SparseProduct.apply(flat, self.weight, self.bias)
        return out.reshape(*x.shape[:-1], self.out_features)
