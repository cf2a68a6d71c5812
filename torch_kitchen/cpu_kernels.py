"""CPU kernels for the models, applied from outside: `accelerate_cpu(network)`.

The models are built from torch's own layers (`nn.Linear`, and the MLP encoders' `ObservationLinear`, an
`nn.Linear` that reads uint8 observations), so a printed model, a compiled graph and a GPU see plain torch. On a
CPU, three faster ways to compute the same products pay (BENCHMARKS.md):

    nn.Linear          -> `OneDNNLinear`            oneDNN's kernels, which use AVX-512 on AMD processors too
    ObservationLinear  -> `SparseInputLinear`       the product from the observation's non-zero entries alone
    EgocentricLinear   -> `SparseEgocentricLinear`  the same for the agent-centred window, by renumbering columns

`accelerate_cpu` swaps each layer's class for its CPU twin in place: the same parameters (the optimizer's, the
checkpoint's keys), the same results to float32 rounding. Each twin still takes torch's own product wherever its
kernel does not apply (another device, under vmap, inside a compiled graph, a product too small to repay it).
"""

from __future__ import annotations

import torch
from torch import nn

from torch_kitchen.egocentric import EgocentricLinear, SparseEgocentricLinear
from torch_kitchen.onednn_linear import OneDNNLinear
from torch_kitchen.sparse_linear import (
    NonZeroEntries,
    ObservationLinear,
    SparseInputLinear,
    remember_entries,
    store_by_column,
)
from torch_kitchen.torchrl_internals import MultiAgentNet

CPU_TWINS = {nn.Linear: OneDNNLinear, ObservationLinear: SparseInputLinear, EgocentricLinear: SparseEgocentricLinear}


def accelerate_cpu(*networks: nn.Module) -> None:
    """Gives every layer of `networks` that has a CPU twin (`CPU_TWINS`) that twin's class, in place (see the module
    docstring); run it before the networks first run, so that each agent's network is built from the twins."""
    for network in networks:
        for module in network.modules():
            twin = CPU_TWINS.get(type(module))
            if twin is not None:
                module.__class__ = twin
                if twin in (SparseInputLinear, SparseEgocentricLinear) and not module.weight.is_meta:
                    store_by_column(module.weight)
        for module in network.modules():
            if isinstance(module, MultiAgentNet):  # its agents' networks as built before the swap
                module.forget_built_networks()
                if module.share_params:
                    for layer in module.shared_net().modules():
                        if isinstance(layer, (SparseInputLinear, SparseEgocentricLinear)):
                            store_by_column(layer.weight)


class BatchObservations:
    """The non-zero entries of a batch's observations [K, T, 2, H, W, C], found once for the PPO epochs: each
    minibatch of whole kitchens gets its own from them (`hand_to`), for the sparse first layers that read it,
    instead of a search of every minibatch (1.4 ms of a 1,024-row minibatch's 10 at JaxMARL's setting)."""

    def __init__(self, observations: torch.Tensor, dtype: torch.dtype = torch.float32):
        self.features = observations.shape[-3:].numel()
        self.rows_per_kitchen = observations[0].numel() // self.features
        self.entries = NonZeroEntries(observations.reshape(-1, self.features), dtype)

    def hand_to(self, observations: torch.Tensor, kitchens: torch.Tensor) -> NonZeroEntries:
        """Hands the entries of the minibatch `observations` (the batch's `kitchens`) to the next layers reading it;
        returns them."""
        entries = self.entries.of_blocks(kitchens, self.rows_per_kitchen)
        remember_entries(observations.reshape(-1, self.features), entries)
        return entries


def batch_observations(networks: list[nn.Module], observations: torch.Tensor) -> BatchObservations | None:
    """The batch's `BatchObservations` where a network reads it through a sparse first layer, on the CPU; else None."""
    sparse = any(isinstance(module, SparseInputLinear) for network in networks for module in network.modules())
    return BatchObservations(observations) if sparse and observations.device.type == "cpu" else None
