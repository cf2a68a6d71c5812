"""Zoo cooks in a learner's kitchens: population play on the Infinite Kitchen.

`ZooSeats(conventions, share, seed)` (a training transform) draws, for every kitchen and every episode, whether a
zoo cook plays in it (with probability `share`), in which seat and with which of the conventions:

    ("agents", "zoo_cook")  long [B, 2]  the convention's index in the seat a zoo cook plays, -1 in the learner's

`ZooPartners(conventions)` (a policy module, after the actor) replaces the action of every seat a zoo cook plays by
the one that cook's convention draws (`torch_kitchen.scripted.ScriptedCook`). The learner plays the other seats; a
learning algorithm trains on those only (`trainers.algorithms.zoo_ippo`).
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded, Composite

from jax_env.cook import CookConvention
from torch_kitchen.conventions import Convention
from torch_kitchen.keys import ACTION, AGENTS, OBSERVATION
from torch_kitchen.partner import PartnerSeats
from torch_kitchen.scripted import ScriptedCook, stacked_conventions

ZOO_COOK = (AGENTS, "zoo_cook")
LEARNER = -1  # the zoo_cook entry of a seat the learner plays


class ZooSeats(PartnerSeats):
    """Per kitchen and episode: a zoo cook with probability `share`, in a seat and with a convention drawn
    uniformly (see the module docstring); resumed draws are those a run without a stop would make."""

    key = ZOO_COOK

    def __init__(self, conventions: int, share: float, seed: int = 0):
        if not 0.0 <= share <= 1.0:
            raise ValueError(f"the share of kitchens with a zoo cook lies in [0, 1], got {share}")
        self.conventions, self.share = conventions, share
        super().__init__(seed)

    def _draw(self, count: int) -> torch.Tensor:
        # Encoded per kitchen: -1 without a zoo cook, else 2 * convention + seat.
        cooks = torch.rand(count, generator=self.generator) < self.share
        seat = torch.randint(2, (count,), generator=self.generator)
        convention = torch.randint(self.conventions, (count,), generator=self.generator)
        return torch.where(cooks, 2 * convention + seat, -1)

    def _seating(self, device) -> torch.Tensor:
        draws = self._seats.to(device)
        seats = torch.arange(2, device=device)
        return torch.where((draws[:, None] >= 0) & (draws[:, None] % 2 == seats), draws[:, None] // 2, LEARNER)

    def _spec(self, agents: Composite):
        return Bounded(LEARNER, self.conventions - 1, shape=agents.shape, dtype=torch.int64, device=agents.device)


class ZooPartners(TensorDictModuleBase):
    """Writes, for every seat a zoo cook plays (`ZOO_COOK` >= 0), the action its convention draws; the learner's
    seats keep theirs. One call of the cook plays every kitchen, each seat by its own convention (the learner's by
    the first, unused), so that batches of any seating share one compiled program."""

    def __init__(self, conventions: list[Convention]):
        super().__init__()
        self.cook = ScriptedCook()
        self.conventions = stacked_conventions(conventions)
        self.in_keys = [ACTION, OBSERVATION, ZOO_COOK]
        self.out_keys = [ACTION]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        zoo_cook, action = tensordict.get(ZOO_COOK), tensordict.get(ACTION)
        seated = zoo_cook.clamp(min=0).flatten().cpu().numpy()  # a convention per seat, [B * 2]
        logits = self.cook(tensordict.get(OBSERVATION), CookConvention(*(leaf[seated] for leaf in self.conventions)))
        drawn = torch.distributions.Categorical(logits=logits, validate_args=False).sample()
        tensordict.set(ACTION, torch.where(zoo_cook >= 0, drawn, action))
        return tensordict
