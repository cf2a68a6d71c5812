"""The kitchen's symmetries: its mirror images and, on square grids, its quarter turns and diagonal reflections.

Overcooked's rules know no left or right: mirror a kitchen and every move action with it, and the game plays out
as the mirror image (`tests/torch_kitchen/test_symmetry.py` checks it step by step). So a labelled observation
seen mirrored is just as true a lesson, and distillation shows the learner each lesson under a random symmetry:
eight kitchens from one on a square grid. A symmetry is a number 0-7: bit 0 mirrors east-west, bit 1 north-south,
bit 2 (square grids only) swaps the axes, applied in that order.
"""

from __future__ import annotations

import functools

import torch

from jax_env import NUM_ACTIONS, Channel

NUM_SYMMETRIES = 8
# Where each direction (NORTH, SOUTH, EAST, WEST) goes under one mirror; move actions 0-3 are the directions.
_MIRROR_EAST_WEST = (0, 1, 3, 2)
_MIRROR_NORTH_SOUTH = (1, 0, 2, 3)
_SWAP_AXES = (3, 2, 1, 0)  # (dx, dy) -> (dy, dx): NORTH <-> WEST, SOUTH <-> EAST


def direction_map(symmetry: int) -> tuple[int, ...]:
    """The direction (and move action) that each direction becomes under `symmetry`."""
    mapped = (0, 1, 2, 3)
    for bit, mirror in enumerate((_MIRROR_EAST_WEST, _MIRROR_NORTH_SOUTH, _SWAP_AXES)):
        if symmetry >> bit & 1:
            mapped = tuple(mirror[d] for d in mapped)
    return mapped


def symmetries_of(height: int, width: int) -> int:
    """How many symmetries a height x width grid has: 8 when square, else the 4 mirror combinations."""
    return NUM_SYMMETRIES if height == width else 4


def transform_observation(observation: torch.Tensor, symmetry: int) -> torch.Tensor:
    """[..., H, W, 26] -> the observation of the kitchen under `symmetry` (facing channels re-labelled)."""
    height, width, channels = observation.shape[-3:]
    source = _source_entries(height, width, channels, symmetry).to(observation.device)
    # One gather of every entry from where it was: about a fifth of the time of two flips, a transpose and a gather
    # of channels, each of which copied the whole batch (0.17 against 0.8-1.0 ms for 256 steps of both seats).
    out_height, out_width = (width, height) if symmetry & 4 else (height, width)
    flat = observation.reshape(-1, height * width * channels)
    moved = torch.gather(flat, 1, source.expand(flat.shape[0], -1))
    return moved.reshape(*observation.shape[:-3], out_height, out_width, channels)


@functools.cache
def _source_entries(height: int, width: int, channels: int, symmetry: int) -> torch.Tensor:
    """int64 [H' * W' * C]: for each entry of the transformed observation, row-major, the flat index of the entry of
    the original it shows."""
    where = torch.arange(height * width * channels).reshape(height, width, channels)
    if symmetry & 1:
        where = where.flip(-2)
    if symmetry & 2:
        where = where.flip(-3)
    if symmetry & 4:
        where = where.transpose(-2, -3)
    order = list(range(channels))
    for facing in (Channel.SELF_FACING, Channel.PARTNER_FACING):
        for direction, mapped in enumerate(direction_map(symmetry)):
            order[facing + mapped] = facing + direction
    return where[..., order].reshape(-1).contiguous()


def transform_action_probs(probs: torch.Tensor, symmetry: int) -> torch.Tensor:
    """[..., 6] action probabilities (or logits) -> those of the mirrored actions under `symmetry`."""
    source = list(range(NUM_ACTIONS))
    for direction, mapped in enumerate(direction_map(symmetry)):
        source[mapped] = direction
    return probs[..., source]

