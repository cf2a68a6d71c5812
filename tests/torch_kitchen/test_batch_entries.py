"""A minibatch's sparse entries taken from its batch's, found once (`torch_kitchen.cpu_kernels.BatchObservations`)."""

import torch

from torch_kitchen.cpu_kernels import BatchObservations
from torch_kitchen.sparse_linear import NonZeroEntries, SparseInputLinear, nonzero_entries


def sparse_observations(generator, shape=(6, 5, 2, 3, 3, 4)):
    """uint8 observations [K, T, 2, H, W, C], mostly zero, some rows empty."""
    values = torch.randint(0, 4, shape, generator=generator, dtype=torch.uint8)
    return values * (torch.rand(shape, generator=generator) < 0.1)


def test_a_minibatchs_entries_taken_from_the_batchs_are_those_a_search_finds():
    generator = torch.Generator().manual_seed(0)
    batch = sparse_observations(generator)
    batch[2] = 0  # a kitchen with no entries at all
    observations = BatchObservations(batch)
    for kitchens in (torch.tensor([4, 1]), torch.tensor([2, 0, 5]), torch.tensor([3])):
        minibatch = batch.index_select(0, kitchens)
        flat = minibatch.reshape(-1, 36)
        found = NonZeroEntries(flat, torch.float32)
        taken = observations.entries.of_blocks(kitchens, observations.rows_per_kitchen)
        assert taken.shape == found.shape
        for name in ("rows", "cols", "values", "row_offsets"):
            assert torch.equal(getattr(taken, name), getattr(found, name)), name
        # The weight's gradient, summed kitchen by kitchen from the batch's x.T of each, is the searched one's.
        grad_out = torch.randn(flat.shape[0], 5, generator=generator)
        torch.testing.assert_close(taken.weight_gradient(grad_out), found.weight_gradient(grad_out))
        torch.testing.assert_close(found.weight_gradient(grad_out), flat.float().t() @ grad_out)
    # Each kitchen's x.T is the CSR matrix a sort of that kitchen's entries alone makes.
    for kitchen, transposed in enumerate(observations.entries._block_transposes(observations.rows_per_kitchen)):
        alone = NonZeroEntries(batch[kitchen].reshape(-1, 36), torch.float32).transposed()
        for part in ("crow_indices", "col_indices", "values"):
            assert torch.equal(getattr(transposed, part)(), getattr(alone, part)()), (kitchen, part)


def test_the_layer_reading_a_minibatch_uses_the_entries_handed_to_it_and_computes_the_same():
    generator = torch.Generator().manual_seed(1)
    batch = sparse_observations(generator)
    layer = SparseInputLinear(36, 8)
    kitchens = torch.tensor([5, 3])
    minibatch = batch.index_select(0, kitchens)
    expected = layer(minibatch.clone().reshape(*minibatch.shape[:-3], 36))
    handed = BatchObservations(batch).hand_to(minibatch, kitchens)
    assert nonzero_entries(minibatch.reshape(-1, 36), torch.float32) is handed
    assert torch.equal(layer(minibatch.reshape(*minibatch.shape[:-3], 36)), expected)
