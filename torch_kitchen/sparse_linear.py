"""A linear layer for mostly-zero inputs: the MLP encoders' first layer.

A kitchen's observation is about 2.5% non-zero (the Infinite Kitchen: some 32 of 7 x 7 x 26 = 1,274 inputs per
agent), and the first layer over it holds most of an MLP's arithmetic: at hidden 256 its forward and weight
gradient are three quarters of a PPO minibatch on a CPU. `SparseInputLinear` computes the same product from the
non-zero entries alone: the forward product as an embedding bag (each row sums the weight columns of its
entries), the weight's gradient as a CSR matrix product. Finding the entries is the larger part of the cost, so
the actor and the critic, which read the same observations, find them once. It is `nn.Linear` in every other respect
(same parameters, state_dict keys and init), so checkpoints and user code see no difference; the sums run in
another order, so results agree with `nn.Linear` to float32 rounding, not bit for bit.

The models are built with the plain `ObservationLinear`; `torch_kitchen.cpu_kernels.accelerate_cpu` makes it a
`SparseInputLinear` on a CPU. Where finding the non-zeros would cost more than it saves, the layer takes the plain
product: on a GPU (whose `nonzero` waits for the device, and whose dense products are cheap), under vmap, and
inside `torch.compile`'s graphs.
"""

from __future__ import annotations

import copy
import threading
import warnings

import torch
from torch import nn
from torch.nn import functional as F

from torch_kitchen.onednn_linear import plain_linear_here

# Only the CSR constructor's notice that its API is in beta: the products used here are CPU kernels of long standing.
warnings.filterwarnings("ignore", message="Sparse CSR tensor support is in beta", category=UserWarning)


def _csr(rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """The CSR matrix of `shape` with `values` at (`rows`, `cols`); the entries sorted by row, then column."""
    return torch.sparse_csr_tensor(_row_offsets(rows, shape[0]), cols, values, shape, check_invariants=False)


def _row_offsets(rows: torch.Tensor, num_rows: int) -> torch.Tensor:
    """int64 [num_rows + 1]: where each row's entries start in `rows` (sorted), then their count."""
    offsets = torch.zeros(num_rows + 1, dtype=torch.int64)
    torch.cumsum(torch.bincount(rows, minlength=num_rows), 0, out=offsets[1:])
    return offsets


class NonZeroEntries:
    """The non-zero entries of a 2-D input x [N, in], row-major: their rows, columns, float values and each row's
    first entry; and, on first use, x.T as a CSR matrix (for the weight's gradient)."""

    def __init__(self, x: torch.Tensor, dtype: torch.dtype):
        self.shape = tuple(x.shape)
        flat_x = x.reshape(-1)
        flat = flat_x.nonzero().squeeze(1)  # a flat index: far cheaper than a 2-D nonzero and gather
        self.rows = torch.div(flat, self.shape[1], rounding_mode="floor")
        self.cols = flat - self.rows * self.shape[1]
        self.values = flat_x.take(flat).to(dtype)
        self.row_offsets = _row_offsets(self.rows, self.shape[0])
        self._transposed = None
        self._of_blocks = None  # (the whole input, blocks, block_rows) of a minibatch taken by `of_blocks`
        self._blocks = None  # `_EntriesByBlock` of the whole input, made on a minibatch's first `transposed`

    def moved(self, cols: torch.Tensor, in_features: int) -> NonZeroEntries:
        """The same entries in other columns `cols` of a wider input [N, in_features] (e.g. a window around
        each row's agent)."""
        entries = copy.copy(self)
        entries.cols, entries.shape, entries._transposed = cols, (self.shape[0], in_features), None
        entries._of_blocks = entries._blocks = None
        return entries

    def of_blocks(self, blocks: torch.Tensor, block_rows: int) -> NonZeroEntries:
        """The entries of the input made of these blocks of `block_rows` rows (block b: rows b * block_rows on), in
        the order given: what `NonZeroEntries` finds in that input, without searching it (a minibatch of whole
        kitchens of a batch whose entries were found once). A block's entries are a slice of this input's; their
        x.T comes from this input's too (`_blocks_transposed`)."""
        spans = _spans(self.row_offsets, blocks, block_rows)
        entries = copy.copy(self)
        entries.shape = (len(spans) * block_rows, self.shape[1])
        entries.cols, entries.values = _joined(self.cols, spans), _joined(self.values, spans)
        entries.rows = _joined(self.rows, spans, _row_shifts(blocks, block_rows))
        entries.row_offsets = _row_offsets(entries.rows, entries.shape[0])
        entries._transposed, entries._blocks = None, None
        entries._of_blocks = (self, blocks, block_rows)
        return entries

    def transposed(self) -> torch.Tensor:
        """x.T as a CSR matrix [in, N]: the entries by column (then by row)."""
        if self._transposed is None:
            if self._of_blocks is not None:
                whole, blocks, block_rows = self._of_blocks
                self._transposed = whole._blocks_transposed(blocks, block_rows)
            else:
                by_col = torch.argsort(self.cols, stable=True)
                self._transposed = _csr(*_gathered(by_col, self.cols, self.rows, self.values), self.shape[::-1])
        return self._transposed

    def _blocks_transposed(self, blocks: torch.Tensor, block_rows: int) -> torch.Tensor:
        """x.T of the input `of_blocks(blocks, block_rows)`, merged from its blocks' own entries sorted by column
        (sorted once per block size, `_by_block`), instead of a sort of its entries: within a column an entry of
        the block in place j comes after those of the blocks before it, in the order of its rows."""
        by_block = self._by_block(block_rows)
        in_features = self.shape[1]
        counts = by_block.counts[blocks]  # [blocks, in]: each block's entries per column
        col_offsets = torch.zeros(in_features + 1, dtype=torch.int64)
        torch.cumsum(counts.sum(0), 0, out=col_offsets[1:])
        # Where block j's entries of column c start in the merged order; each entry goes there plus its rank.
        starts = (col_offsets[:-1] + counts.cumsum(0) - counts).reshape(-1)
        spans = _spans(by_block.starts, blocks, 1)
        places = [place * in_features for place in range(len(spans))]
        destination = starts.index_select(0, _joined(by_block.cols, spans, places)) + _joined(by_block.ranks, spans)
        rows = _joined(by_block.rows, spans, _row_shifts(blocks, block_rows))
        values = _joined(by_block.values, spans)
        merged_rows = torch.empty_like(rows).scatter_(0, destination, rows)  # scatter_: 4x the speed of [] = on a CPU
        merged_values = torch.empty_like(values).scatter_(0, destination, values)
        return torch.sparse_csr_tensor(col_offsets, merged_rows, merged_values,
                                       (in_features, len(blocks) * block_rows), check_invariants=False)

    def _by_block(self, block_rows: int) -> _EntriesByBlock:
        if self._blocks is None or self._blocks.block_rows != block_rows:
            self._blocks = _EntriesByBlock(self, block_rows)
        return self._blocks


def _spans(offsets: torch.Tensor, blocks: torch.Tensor, block_rows: int) -> list[tuple[int, int]]:
    """(start, end) in entries sorted by row of each block's entries, from the rows' `offsets`."""
    return list(zip(offsets[blocks * block_rows].tolist(), offsets[(blocks + 1) * block_rows].tolist()))


def _row_shifts(blocks: torch.Tensor, block_rows: int) -> list[int]:
    """What turns a block's rows in the whole input into its rows in the input of `blocks` in that order."""
    return [(place - block) * block_rows for place, block in enumerate(blocks.tolist())]


def _joined(tensor: torch.Tensor, spans: list[tuple[int, int]], shifts: list[int] | None = None) -> torch.Tensor:
    """The `spans` of `tensor` one after another, each plus its shift."""
    if shifts is None:
        return torch.cat([tensor[start:end] for start, end in spans])
    return torch.cat([tensor[start:end] + shift for (start, end), shift in zip(spans, shifts)])


def _gathered(order: torch.Tensor, *parts: torch.Tensor) -> tuple[torch.Tensor, ...]:
    """Each part in `order`, by index_select: a third of the time of indexing with [] on a CPU."""
    return tuple(part.index_select(0, order) for part in parts)


class _EntriesByBlock:
    """An input's entries ordered by block of `block_rows` rows, then column, then row (one sort for the PPO
    epochs): each block's count per column, and each entry's rank among its block's entries of its column."""

    def __init__(self, entries: NonZeroEntries, block_rows: int):
        self.block_rows = block_rows
        in_features, num_blocks = entries.shape[1], entries.shape[0] // block_rows
        key = torch.div(entries.rows, block_rows, rounding_mode="floor") * in_features + entries.cols
        order = torch.argsort(key, stable=True)
        self.rows, self.cols, self.values, key = _gathered(order, entries.rows, entries.cols, entries.values, key)
        self.counts = torch.bincount(key, minlength=num_blocks * in_features).reshape(num_blocks, in_features)
        self.starts = entries.row_offsets[torch.arange(num_blocks + 1) * block_rows]
        group_starts = torch.cat([torch.zeros(1, dtype=torch.int64), self.counts.reshape(-1).cumsum(0)[:-1]])
        self.ranks = torch.arange(len(order)) - group_starts.index_select(0, key)


class _LastInput(threading.local):
    """The last input whose entries were found, per thread (teams learn on threads of their own): the actor and
    the critic read the same observations, so the second finds them here."""

    tensor: torch.Tensor | None = None
    key: tuple = ()
    entries: NonZeroEntries | None = None


_last_input = _LastInput()


def nonzero_entries(x: torch.Tensor, dtype: torch.dtype) -> NonZeroEntries:
    """x's `NonZeroEntries`, found once for consecutive calls on the same unchanged data.

    Two calls see the same data when their tensors share storage, offset, shape, strides and version counter;
    the last input is held, so its memory cannot be reused by another tensor meanwhile. Inference tensors, which
    have no version counter, are not remembered.
    """
    if x.is_inference():
        return NonZeroEntries(x, dtype)
    if _last_input.tensor is None or _last_input.key != _input_key(x, dtype):
        remember_entries(x, NonZeroEntries(x, dtype))
    return _last_input.entries


def _input_key(x: torch.Tensor, dtype: torch.dtype) -> tuple:
    """What tells x's data apart from any other's while x is held: storage, offset, shape, strides, version."""
    return x.untyped_storage().data_ptr(), x.storage_offset(), x.shape, x.stride(), x._version, dtype


def remember_entries(x: torch.Tensor, entries: NonZeroEntries) -> None:
    """Hands x's entries (found by a search, or another way: `NonZeroEntries.of_blocks`) to the next layers that
    read x; not for inference tensors, which have no version counter."""
    if not x.is_inference():
        _last_input.tensor, _last_input.key, _last_input.entries = x, _input_key(x, entries.values.dtype), entries


class SparseProduct(torch.autograd.Function):
    """x @ weight.T + bias from x's non-zero entries: x [N, in] (any real dtype; uint8 observations are read as
    they are), weight float [out, in], bias [out] -> float [N, out]."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, entries: NonZeroEntries
                ) -> torch.Tensor:
        """entries: x's `nonzero_entries`, or them moved to the columns of `weight` (then x takes no gradient)."""
        ctx.save_for_backward(weight)
        ctx.entries = entries
        # Each row sums its entries' weight columns: an embedding bag over the rows of weight.T (contiguous as the
        # layer stores it; copied so otherwise: a strided read is 15x slower at a minibatch's size).
        out = F.embedding_bag(entries.cols, weight.t().contiguous(), entries.row_offsets[:-1], mode="sum",
                              per_sample_weights=entries.values)
        return out.add_(bias)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        (weight,) = ctx.saved_tensors
        grad_x = grad_weight = grad_bias = None
        if ctx.needs_input_grad[0]:  # observations never need it; other inputs might
            grad_x = grad_out @ weight
        if ctx.needs_input_grad[1]:  # grad_out.T @ x, as (x.T @ grad_out).T
            grad_weight = torch.sparse.mm(ctx.entries.transposed(), grad_out).t()
        if ctx.needs_input_grad[2]:
            grad_bias = grad_out.sum(0)
        return grad_x, grad_weight, grad_bias, None


class ObservationLinear(nn.Linear):
    """`nn.Linear` over inputs of any real dtype (uint8 observations are cast to the weight's): [..., in_features]
    -> float [..., out_features]. The MLP encoders' first layer; on a CPU, `accelerate_cpu` makes it a
    `SparseInputLinear`."""

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return F.linear(x.to(self.weight.dtype), self.weight, self.bias)


def store_by_column(weight: nn.Parameter) -> None:
    """Lays out a [out, in] weight column by column, in place (the same Parameter): the sparse product's embedding
    bag reads weight.T's rows, which are then contiguous without a copy (0.12 ms at hidden 256, twice per
    collection step), and the weight's gradient comes out in this layout already."""
    if weight.t().is_contiguous():
        return
    weight.data = weight.data.t().contiguous().t()


class SparseInputLinear(ObservationLinear):
    """`ObservationLinear` computed from the non-zero entries of its input, on CPU (see the module docstring);
    made by `torch_kitchen.cpu_kernels.accelerate_cpu`.

    [..., in_features] of any real dtype (uint8 observations need no cast) -> float [..., out_features]; a layer
    with a bias, its weight stored column by column (`store_by_column`).
    """

    def __init__(self, *args, **kwargs):
        super().__init__(*args, **kwargs)
        store_by_column(self.weight)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        # `nonzero` has no batched form under vmap and would stop torch.compile's graph.
        if plain_linear_here(x, self.weight):
            return super().forward(x)
        flat = x.reshape(-1, self.in_features)
        out = SparseProduct.apply(flat, self.weight, self.bias, nonzero_entries(flat, self.weight.dtype))
        return out.reshape(*x.shape[:-1], self.out_features)
