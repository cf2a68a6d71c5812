import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from human_proxy_states import state_figures  # noqa: E402

from jax_env.observation import Channel  # noqa: E402


def test_held_items_busy_pots_and_counter_items_are_told_apart():
    view = torch.zeros(2, 2, 4, 5, 26, dtype=torch.uint8)  # two steps of a 4x5 kitchen, seat 0's view first
    view[:, 0, 1, 1, Channel.SELF] = view[:, 0, 2, 3, Channel.PARTNER] = 1
    view[:, 0, 1, 1, Channel.ONION] = 1  # held by the first cook
    view[:, 0, 0, 2, Channel.PLATE] = view[:, 0, 3, 2, Channel.ONION] = 1  # lying on counters
    view[:, 0, 0, 4, Channel.POT] = view[:, 0, 3, 4, Channel.POT] = 1
    view[0, 0, 0, 4, Channel.COOKING_OR_SOUP] = 3  # the first pot cooks at the first step, ready at the second
    view[1, 0, 0, 4, Channel.COOKING_OR_SOUP] = view[1, 0, 0, 4, Channel.SOUP] = 3
    onion, plate, soup, busy, ready, onions_lying, plates_lying = state_figures(view)
    assert (onion, plate, soup) == (0.5, 0.0, 0.0)  # one cook of two holds an onion
    assert (busy, ready) == (0.5, 0.25)  # of the 4 pot-steps: 2 cooking or ready, 1 ready
    assert (onions_lying, plates_lying) == (1.0, 1.0)
