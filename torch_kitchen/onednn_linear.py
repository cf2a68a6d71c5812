"""A linear layer whose CPU products run in oneDNN: the models' dense layers.

Torch's float32 CPU matrix products go to MKL, which takes its AVX-512 kernels on Intel processors alone: on an
AMD processor with AVX-512 (Zen 4 and later) it runs the AVX2 ones, at half the speed the chip allows. oneDNN,
which torch also carries, chooses its kernels by the instructions the processor has. `OneDNNLinear` is `nn.Linear`
in every respect (parameters, state_dict keys, init) but computes its forward product and both gradient products
with oneDNN on CPU: on a Zen 5 core, 2.2x MKL's speed for a 4,096 x 256 x 256 product. The sums run in another
order, so results agree with `nn.Linear` to float32 rounding, not bit for bit.

It is a plain `nn.Linear` where torch has no oneDNN, on other devices, under vmap (per-agent networks), inside
`torch.compile`'s graphs (which choose their own kernels), and for products too small to repay a oneDNN call.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch
from torch import nn
from torch.nn import functional as F


def _onednn_linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
    """x [N, in] @ weight[out, in].T + bias, in oneDNN (strided operands are read as they are)."""
    return torch.ops.mkldnn._linear_pointwise(x, weight, bias, "none", [], "")


class OneDNNProduct(torch.autograd.Function):
    """x @ weight.T + bias with its gradients, all three products in oneDNN: x float [N, in], weight [out, in],
    bias [out] or None -> [N, out]."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None) -> torch.Tensor:
        ctx.save_for_backward(x, weight)
        ctx.has_bias = bias is not None
        return _onednn_linear(x, weight, bias)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        x, weight = ctx.saved_tensors
        grad_x = grad_weight = grad_bias = None
        if ctx.needs_input_grad[0]:
            grad_x = _onednn_linear(grad_out, weight.t(), None)  # grad_out @ weight
        if ctx.needs_input_grad[1]:
            grad_weight = _onednn_linear(grad_out.t(), x.t(), None)  # grad_out.T @ x
        if ctx.has_bias and ctx.needs_input_grad[2]:
            grad_bias = grad_out.sum(0)
        return grad_x, grad_weight, grad_bias


def onednn_available() -> bool:
    """Whether this torch carries oneDNN's linear kernel."""
    return torch.backends.mkldnn.is_available() and hasattr(torch.ops.mkldnn, "_linear_pointwise")


_ONEDNN = onednn_available()


def _under_vmap(x: torch.Tensor) -> bool:
    """Whether `x` is a slice of a vmapped batch (separate networks per agent run under TorchRL's vmap)."""
    return torch._C._functorch.is_batchedtensor(x)


_device_path = False  # set by `device_path()`


@contextlib.contextmanager
def device_path() -> Iterator[None]:
    """Inside it the layers take torch's own products on the CPU too, as they do on a GPU: what a GPU would run,
    counted or compiled on a machine without one."""
    global _device_path
    outer, _device_path = _device_path, True
    try:
        yield
    finally:
        _device_path = outer


def plain_linear_here(x: torch.Tensor, weight: torch.Tensor, in_graph: bool = False) -> bool:
    """Whether a layer should take torch's own product for `x`: off the CPU, under vmap, inside compiled graphs
    (unless the layer's kernel is an operator a graph can call: `in_graph`), inside `device_path()`."""
    return (_device_path or x.device.type != "cpu" or (torch.compiler.is_compiling() and not in_graph)
            or _under_vmap(x) or _under_vmap(weight))


# Below this many multiply-adds a oneDNN call's fixed cost (about 20 us on a Zen 5 core) and the copies its weight
# gradient makes of transposed operands outweigh its faster kernels. At 32 rows x 64 x 64 (acting in 16 kitchens)
# torch's product takes 5 us; at 1,024 rows x 64 x 64 (a minibatch at JaxMARL's setting, 2^22) on a Zen 4 core the
# forward products tie (93 us) and torch's weight gradient takes 98 us against oneDNN's 140 and a 124 us copy, so
# such minibatches learn about 8% faster with torch's (BENCHMARKS.md, "Small products in torch's kernels").
ONEDNN_MIN_PRODUCT = 1 << 23


class OneDNNLinear(nn.Linear):
    """`nn.Linear` computed by oneDNN on CPU (see the module docstring): float [..., in_features] -> float
    [..., out_features]. Small products (`ONEDNN_MIN_PRODUCT`) take torch's own."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if (not _ONEDNN or x.dtype != torch.float32 or plain_linear_here(x, self.weight)
                or x.numel() * self.out_features < ONEDNN_MIN_PRODUCT):
            return F.linear(x, self.weight, self.bias)
        out = OneDNNProduct.apply(x.reshape(-1, self.in_features), self.weight, self.bias)
        return out.reshape(*x.shape[:-1], self.out_features)
