"""Zoo cooks in a learner's kitchens: population play on the Infinite Kitchen.

`ZooSeats(conventions, share, seed)` (a training transform) draws, for every kitchen and every episode, whether a
zoo cook plays in it (with probability `share`), in which seat and with which of the conventions:

    ("agents", "zoo_cook")  long [B, 2]  the convention's index in the seat a zoo cook plays, -1 in the learner's

`ZooPartners(conventions)` (a policy module, after the actor) replaces the action of every seat a zoo cook plays by the
one that cook's convention draws (`torch_kitchen.partners.scripted_cook.ScriptedCook`). The learner plays the other
seats; a learning algorithm trains on those only (`trainers.algorithms.zoo_ippo`).

Inside the kitchens' XLA rollout (`torch_kitchen.xla_rollout`) the same seats are drawn and the same cooks act in the
program, by `draw_seats`, `seating` and `cook_actions`, from keys the seats' generator hands out once per batch.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.data import Bounded, Composite

from jax_env.cook import CookConvention, cook_logits
from torch_kitchen.keys import ACTION, AGENTS, OBSERVATION
from torch_kitchen.models.e3t_partner import PartnerSeats
from torch_kitchen.partners.conventions import Convention
from torch_kitchen.partners.scripted_cook import ScriptedCook, stacked_conventions

ZOO_COOK = (AGENTS, "zoo_cook")
LEARNER = -1  # the zoo_cook entry of a seat the learner plays


def draw_seats(key: jax.Array, count: int, conventions: int, share: float) -> jax.Array:
    """int32 [count]: `ZooSeats`' draws inside a JAX program, encoded as there: -1 without a zoo cook (probability
    1 - `share`), else 2 * convention + seat."""
    cooks, seats, drawn = jax.random.split(key, 3)
    cook = jax.random.uniform(cooks, (count,)) < share
    seat = jax.random.randint(seats, (count,), 0, 2)
    convention = jax.random.randint(drawn, (count,), 0, conventions)
    return jnp.where(cook, 2 * convention + seat, LEARNER)


def seating(draws: jax.Array) -> jax.Array:
    """int32 [B, 2], the `ZOO_COOK` entry of draws [B]: the convention in the seat a zoo cook plays, -1 elsewhere."""
    seats = jnp.arange(2)
    return jnp.where((draws[:, None] >= 0) & (draws[:, None] % 2 == seats), draws[:, None] // 2, LEARNER)


def cook_actions(key: jax.Array, observation: jax.Array, action: jax.Array, draws: jax.Array,
                 conventions: CookConvention, kitchens_at_most: int | None = None,
                 tables: jax.Array | None = None) -> jax.Array:
    """int [B, 2]: `action` with every seat a zoo cook plays (draws [B]) taking the action its convention draws
    (`conventions`: arrays [C, ...]) on its view of observation [B, 2, H, W, C]. A cook plans in its own seat, in
    the kitchens it plays in; `kitchens_at_most` (static): planned for that many kitchens while no more have a cook,
    else for all of them (a CPU's saving, a branch the host reads: None on a GPU, every kitchen's plan drawn).
    `tables`: the kitchens' `floor_tables` [B, ...], kept through their episodes (else the cooks run their waves)."""
    count = len(draws)
    seat = jnp.maximum(draws, 0) % 2
    views = jnp.take_along_axis(observation, seat.reshape(-1, 1, 1, 1, 1), axis=1)[:, 0]

    def planned(kitchens):  # the cooks' draws in these kitchens (int [K], `count` where none: dropped)
        rows = jax.tree.map(lambda leaf: jnp.asarray(leaf)[jnp.maximum(draws[kitchens], 0) // 2], conventions)
        floor = None if tables is None else tables[kitchens]
        logits = cook_logits(views[kitchens], rows, floor, detour_rows=max(1, len(kitchens) // 4),
                             seats=seat[kitchens])
        return jnp.zeros(count, action.dtype).at[kitchens].set(
            jax.random.categorical(key, logits).astype(action.dtype), mode="drop")

    if kitchens_at_most is None or kitchens_at_most >= count:
        drawn = planned(jnp.arange(count))
    else:
        cooks = draws >= 0
        drawn = jax.lax.cond(cooks.sum() <= kitchens_at_most,
                             lambda: planned(jnp.nonzero(cooks, size=kitchens_at_most, fill_value=count)[0]),
                             lambda: planned(jnp.arange(count)))
    return jnp.where(seating(draws) >= 0, drawn[:, None], action)


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
