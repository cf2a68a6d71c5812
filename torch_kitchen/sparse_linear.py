"""A linear layer for mostly-zero inputs: the MLP encoders' first layer.

A kitchen's observation is about 2.5% non-zero (the Infinite Kitchen: some 32 of 7 x 7 x 26 = 1,274 inputs per
agent), and the first layer over it holds most of an MLP's arithmetic: at hidden 256 its forward and weight
gradient are three quarters of a PPO minibatch on a CPU. `SparseInputLinear` computes the same product from the
non-zero entries alone: the forward product as an embedding bag (each row sums the weight columns of its
entries), the weight's gradient as CSR matrix products. Finding the entries is the larger part of the cost, so
the actor and the critic, which read the same observations, find them once. It is `nn.Linear` in every other respect
(same parameters, state_dict keys and init), so checkpoints and user code see no difference; the sums run in
another order, so results agree with `nn.Linear` to float32 rounding, not bit for bit.

The models are built with the plain `ObservationLinear`; `torch_kitchen.cpu_kernels.accelerate_cpu` makes it a
`SparseInputLinear` on a CPU. Where finding the non-zeros would cost more than it saves, the layer takes the plain
product: on a GPU (whose `nonzero` waits for the device, and whose dense products are cheap) and under vmap. Inside
a CPU's compiled graph the product is one operator of the graph (`sparse_input_linear`), whose entries are found
or handed outside it, by the data of its input: the rest of a compiled PPO step then loses its Python, and the
first layer keeps its sparse arithmetic.
"""

from __future__ import annotations

import copy
import threading
import warnings
from collections.abc import Callable

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
        flat = flat_nonzero(flat_x)  # a flat index: far cheaper than a 2-D nonzero and gather
        self.rows = torch.div(flat, self.shape[1], rounding_mode="floor")
        self.cols = flat - self.rows * self.shape[1]
        self.values = flat_x.take(flat).to(dtype)
        self.row_offsets = _row_offsets(self.rows, self.shape[0])
        self._transposed = None
        self._of_blocks = None  # (the whole input, blocks, block_rows) of a minibatch taken by `of_blocks`
        self._blocks = None  # (block_rows, each block's x.T) of the whole input, made on a minibatch's first use
        self._derived = {}  # what `derived` built from these entries, by key

    def moved(self, cols: torch.Tensor, in_features: int) -> NonZeroEntries:
        """The same entries in other columns `cols` of a wider input [N, in_features] (e.g. a window around
        each row's agent)."""
        entries = copy.copy(self)
        entries.cols, entries.shape, entries._transposed = cols, (self.shape[0], in_features), None
        entries._of_blocks = entries._blocks = None
        entries._derived = {}
        return entries

    def derived(self, key: tuple, make: Callable[[], NonZeroEntries]) -> NonZeroEntries:
        """What `make()` builds from these entries (e.g. them `moved` into a window), built once per `key`: the
        layers that read the same input (an actor's and a critic's) share it, its x.T included."""
        if key not in self._derived:
            self._derived[key] = make()
        return self._derived[key]

    def of_blocks(self, blocks: torch.Tensor, block_rows: int) -> NonZeroEntries:
        """The entries of the input made of these blocks of `block_rows` rows (block b: rows b * block_rows on), in
        the order given: what `NonZeroEntries` finds in that input, without searching it (a minibatch of whole
        kitchens of a batch whose entries were found once). A block's entries are a slice of this input's; the
        weight's gradient comes from this input's blocks too (`weight_gradient`)."""
        spans = _spans(self.row_offsets, blocks, block_rows)
        entries = copy.copy(self)
        entries.shape = (len(spans) * block_rows, self.shape[1])
        entries.cols, entries.values = _joined(self.cols, spans), _joined(self.values, spans)
        entries.rows = _joined(self.rows, spans, _row_shifts(blocks, block_rows))
        entries.row_offsets = _row_offsets(entries.rows, entries.shape[0])
        entries._transposed, entries._blocks, entries._derived = None, None, {}
        entries._of_blocks = (self, blocks, block_rows)
        return entries

    def transposed(self) -> torch.Tensor:
        """x.T as a CSR matrix [in, N]: the entries by column (then by row)."""
        if self._transposed is None:
            by_col = stable_order(self.cols, self.shape[1])
            self._transposed = _csr(*_gathered(by_col, self.cols, self.rows, self.values), self.shape[::-1])
        return self._transposed

    def weight_gradient(self, grad_out: torch.Tensor) -> torch.Tensor:
        """x.T @ grad_out [in, out]: a linear layer's weight gradient (transposed) from x's entries. For the input
        of `of_blocks`, the sum of its blocks' own products, each block's x.T made once for the PPO epochs
        (`_block_transposes`): a minibatch then needs no x.T of its own, which took longer than both its
        products."""
        if self._of_blocks is None:
            return torch.sparse.mm(self.transposed(), grad_out)
        whole, blocks, block_rows = self._of_blocks
        transposes = whole._block_transposes(block_rows)
        parts = [torch.sparse.mm(transposes[block], grad_part)
                 for block, grad_part in zip(blocks.tolist(), grad_out.split(block_rows))]
        gradient = parts[0]
        for part in parts[1:]:
            gradient.add_(part)
        return gradient

    def _block_transposes(self, block_rows: int) -> list[torch.Tensor]:
        """x.T of each block of `block_rows` rows of this input, as CSR matrices [in, block_rows]: the entries
        sorted by block, then column, then row, once for the PPO epochs, and cut into blocks."""
        if self._blocks is None or self._blocks[0] != block_rows:
            in_features, num_blocks = self.shape[1], self.shape[0] // block_rows
            blocks = torch.div(self.rows, block_rows, rounding_mode="floor")
            key = blocks * in_features + self.cols
            order = stable_order(key, num_blocks * in_features)
            rows, values = _gathered(order, self.rows - blocks * block_rows, self.values)
            col_counts = torch.bincount(key, minlength=num_blocks * in_features).reshape(num_blocks, in_features)
            col_offsets = torch.zeros(num_blocks, in_features + 1, dtype=torch.int64)
            torch.cumsum(col_counts, 1, out=col_offsets[:, 1:])
            starts = self.row_offsets[torch.arange(num_blocks + 1) * block_rows].tolist()
            transposes = [torch.sparse_csr_tensor(col_offsets[block], rows[start:end], values[start:end],
                                                  (in_features, block_rows), check_invariants=False)
                          for block, (start, end) in enumerate(zip(starts[:-1], starts[1:]))]
            self._blocks = (block_rows, transposes)
        return self._blocks[1]


def flat_nonzero(flat: torch.Tensor) -> torch.Tensor:
    """int64: where the 1-D `flat` is non-zero, in order (`flat.nonzero()`). A batch's observations are searched
    8 bytes at a time first: their 8-byte words are three quarters zero, and the search then reads each element of
    the rest in its own dtype (so -0.0 stays zero), 1.5x as fast as a search element by element."""
    per_word = 8 // flat.element_size()
    if len(flat) < WORD_SEARCH_MIN or per_word < 2 or not flat.is_contiguous() or len(flat) % per_word:
        return flat.nonzero().squeeze(1)
    words = flat.view(torch.int64)
    nonzero_words = words.nonzero().squeeze(1)
    within = words.index_select(0, nonzero_words).view(flat.dtype).nonzero().squeeze(1)
    return nonzero_words.index_select(0, within.div(per_word, rounding_mode="floor")) * per_word + within % per_word


WORD_SEARCH_MIN = 1 << 18  # elements: below it (an acting pass's observations) the second search costs more


def stable_order(keys: torch.Tensor, bound: int) -> torch.Tensor:
    """The stable argsort of integer `keys` in [0, bound), sorted in the narrowest integer type that holds them: a
    CPU sorts int16 keys 5x, int32 keys 2x as fast as int64 ones."""
    narrow = next((dtype for dtype in (torch.int16, torch.int32) if bound <= torch.iinfo(dtype).max + 1), keys.dtype)
    return torch.argsort(keys.to(narrow), stable=True)


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


def sparse_product(entries: NonZeroEntries, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """x @ weight.T + bias from x's `entries`: each row sums its entries' weight columns, an embedding bag over the
    rows of weight.T (contiguous as the layer stores it; copied so otherwise: a strided read is 15x slower at a
    minibatch's size)."""
    out = F.embedding_bag(entries.cols, weight.t().contiguous(), entries.row_offsets[:-1], mode="sum",
                          per_sample_weights=entries.values)
    return out.add_(bias)


class SparseProduct(torch.autograd.Function):
    """x @ weight.T + bias from x's non-zero entries: x [N, in] (any real dtype; uint8 observations are read as
    they are), weight float [out, in], bias [out] -> float [N, out]."""

    @staticmethod
    def forward(ctx, x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor, entries: NonZeroEntries
                ) -> torch.Tensor:
        """entries: x's `nonzero_entries`, or them moved to the columns of `weight` (then x takes no gradient)."""
        ctx.save_for_backward(weight)
        ctx.entries = entries
        return sparse_product(entries, weight, bias)

    @staticmethod
    def backward(ctx, grad_out: torch.Tensor):
        (weight,) = ctx.saved_tensors
        grad_x = grad_weight = grad_bias = None
        if ctx.needs_input_grad[0]:  # observations never need it; other inputs might
            grad_x = grad_out @ weight
        if ctx.needs_input_grad[1]:  # grad_out.T @ x, as (x.T @ grad_out).T
            grad_weight = ctx.entries.weight_gradient(grad_out).t()
        if ctx.needs_input_grad[2]:
            grad_bias = grad_out.sum(0)
        return grad_x, grad_weight, grad_bias, None


@torch.library.custom_op("kitchen::sparse_input_linear", mutates_args=())
def sparse_input_linear(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    """`SparseProduct` as one operator that a compiled graph calls as it is: x [N, in] -> float [N, out], from
    x's `nonzero_entries` (found, or handed to the layers outside the graph, by the data of x)."""
    return sparse_product(nonzero_entries(x, weight.dtype), weight, bias)


@sparse_input_linear.register_fake
def _(x: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor) -> torch.Tensor:
    return weight.new_empty((x.shape[0], weight.shape[0]))


@torch.library.custom_op("kitchen::sparse_input_weight_gradient", mutates_args=())
def sparse_input_weight_gradient(x: torch.Tensor, grad_out: torch.Tensor) -> torch.Tensor:
    """x.T @ grad_out [in, out] from x's `nonzero_entries` (`NonZeroEntries.weight_gradient`)."""
    return nonzero_entries(x, grad_out.dtype).weight_gradient(grad_out)


@sparse_input_weight_gradient.register_fake
def _(x: torch.Tensor, grad_out: torch.Tensor) -> torch.Tensor:
    return grad_out.new_empty((x.shape[1], grad_out.shape[1]))


def _save_input(ctx, inputs, output) -> None:
    ctx.save_for_backward(inputs[0], inputs[1])


def _sparse_input_backward(ctx, grad_out: torch.Tensor):
    x, weight = ctx.saved_tensors
    grad_x = grad_out @ weight if ctx.needs_input_grad[0] else None  # observations never need it
    return grad_x, sparse_input_weight_gradient(x, grad_out).t(), grad_out.sum(0)


sparse_input_linear.register_autograd(_sparse_input_backward, setup_context=_save_input)


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
        # `nonzero` has no batched form under vmap; a compiled graph calls the product as one operator.
        if plain_linear_here(x, self.weight, in_graph=True):
            return super().forward(x)
        flat = x.reshape(-1, self.in_features)
        if torch.compiler.is_compiling():
            out = sparse_input_linear(flat, self.weight, self.bias)
        else:
            out = SparseProduct.apply(flat, self.weight, self.bias, nonzero_entries(flat, self.weight.dtype))
        return out.reshape(*x.shape[:-1], self.out_features)
