"""The one rollout routine of training and evaluation: a TorchRL collector over a `KitchenEnv`, by default the
kitchens' own (`torch_kitchen.rollout.KitchenCollector`, the batches of TorchRL's `Collector` written in place).

Training iterates over it batch after batch; evaluation takes whole episodes from it. Both read the episode
results the same way, from the "episode_deliveries" the env reports on each episode's last step.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from torchrl.collectors import BaseCollector, Collector
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType

from jax_env import Channel
from torch_kitchen.events import kitchen_events
from torch_kitchen.keys import LOGITS, SHAPED_REWARD
from torch_kitchen.rollout import KitchenCollector
from torch_kitchen.xla_rollout import SeatedCollector, XlaCollector, seated_teams, xla_chains


def make_collector(env: EnvBase, policy, frames_per_batch: int, total_frames: int = -1,
                   kind: str = "kitchen") -> BaseCollector:
    """A synchronous collector that samples actions from `policy` (ExplorationType.RANDOM): the kitchens' own
    (`kind="kitchen"`) or TorchRL's `Collector` ("torchrl"), which collect the same batches; or the whole rollout
    inside XLA ("xla", `XlaCollector`: actions drawn by JAX) where it runs the policy's teams, else the kitchens'
    own. XLA runs acting passes (MLP, ego_mlp, GNN; shared by the agents or one network per agent) on a bare
    `KitchenEnv`, and their recurrent variants ("mlp_lstm", "gnn_lstm") on a `KitchenEnv` with the model's
    transforms alone (`with_model_transforms`), with zoo cooks beside one team or not (`zoo_ippo`: its seats and
    cooks play inside the program too) or a teacher guiding one (`GuidedPolicy`, distillation's), and evaluation's
    seated teams (`make_seated_actor`: feed-forward teams and
    scripted cooks, `SeatedCollector`) on a bare `KitchenEnv`; E3T and other transforms, and other acting modules,
    take the kitchens' own.

    Each writes every batch into the same buffers instead of a fresh copy, which keeps large batches cheap;
    consume a batch before asking for the next one.
    """
    if kind == "xla" and xla_chains(env, policy) is not None:
        return XlaCollector(env, policy, frames_per_batch, total_frames)
    if kind == "xla" and seated_teams(env, policy) is not None:
        return SeatedCollector(env, policy, frames_per_batch, total_frames)
    if kind in ("kitchen", "xla"):
        return KitchenCollector(env, policy, frames_per_batch, total_frames)
    return Collector(
        env,
        policy,
        frames_per_batch=frames_per_batch,
        total_frames=total_frames,
        return_same_td=True,
        exploration_type=ExplorationType.RANDOM,
        auto_register_policy_transforms=False,  # the env already carries what the model needs
        track_traj_ids=False,  # nothing reads them, and keeping them up to date costs time at every step
    )


def finished_episode_deliveries(batch: TensorDictBase) -> torch.Tensor:
    """float32 [n]: the deliveries of every episode that ended inside `batch` ([B, T] from a collector)."""
    done = batch["next", "done"].squeeze(-1)
    return batch["next", "episode_deliveries"].squeeze(-1)[done]


@dataclass
class EpisodeOutcomes:
    """One episode of every kitchen: deliveries float32 [B], visits float32 [B, 2, H, W], the steps each agent spent
    on each cell, and events float32 [B, 2, E], how often each agent made each of `torch_kitchen.events.EVENTS`
    happen."""

    deliveries: torch.Tensor
    visits: torch.Tensor
    events: torch.Tensor


def play_episodes(env: EnvBase, policy, max_steps: int, max_frames: int = 1 << 17, kind: str = "kitchen"
                  ) -> EpisodeOutcomes:
    """One episode of every kitchen of `env` (all starting at the collector's reset), read on the fly, by the
    collector `kind` names (`make_collector`).

    The collector hands the episodes over in pieces of at most `max_frames` steps, so memory stays bounded
    however many kitchens play; only the outcomes are kept.
    """
    num_envs = env.batch_size[0]
    steps = max(d for d in range(1, max_steps + 1) if max_steps % d == 0 and d * num_envs <= max(max_frames, num_envs))
    collector = make_collector(env, policy, frames_per_batch=num_envs * steps, total_frames=num_envs * max_steps,
                               kind=kind)
    deliveries, visits, events = None, 0, 0
    try:
        for batch in collector:
            observation = batch["agents", "observation"]
            visits = visits + observation[..., Channel.SELF].sum(1, dtype=torch.float32)
            events = events + kitchen_events(observation, batch["agents", "action"],
                                             batch["next", "agents", "observation"]).sum(1)
            done = batch["next", "done"].squeeze(-1)
            if deliveries is None:
                deliveries = torch.full((num_envs,), float("nan"), device=done.device)
            ended = done.any(1)
            deliveries[ended] = batch["next", "episode_deliveries"].squeeze(-1)[done].to(deliveries.dtype)
    finally:
        collector.shutdown()
    return EpisodeOutcomes(deliveries, visits, events)


# What a batch holds for GAE and the logs alone, which no loss reads: the next step's entries, the episode flags
# and counts, and the acting pass's logits and shaped rewards.
COLLECTION_ONLY = ("next", "done", "terminated", "truncated", "deliveries", "episode_deliveries", LOGITS,
                   SHAPED_REWARD)


def learning_entries(batch: TensorDictBase) -> TensorDictBase:
    """The batch without its `COLLECTION_ONLY` entries (a view): the losses' minibatches gather and carry only
    what they read, and TorchRL's loss walks fewer keys (at JaxMARL's setting a fifth of an update's time)."""
    return batch.exclude(*COLLECTION_ONLY)


def select_kitchens(batch: TensorDictBase, kitchens: torch.Tensor) -> TensorDictBase:
    """batch[kitchens], the rows of those kitchens, gathered by `index_select`: indexing with a tensor gathers the
    uint8 observations element by element, 9x slower."""
    return batch.apply(lambda value: value.index_select(0, kitchens),
                       batch_size=torch.Size([len(kitchens), *batch.batch_size[1:]]))
