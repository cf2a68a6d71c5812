"""The one rollout routine of training and evaluation: a TorchRL `Collector` over a `KitchenEnv`.

Training iterates over it batch after batch; evaluation takes whole episodes from it. Both read the episode
results the same way, from the "episode_deliveries" the env reports on each episode's last step.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from torchrl.collectors import Collector
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType


def make_collector(env: EnvBase, policy, frames_per_batch: int, total_frames: int = -1) -> Collector:
    """A synchronous collector that samples actions from `policy` (ExplorationType.RANDOM).

    `return_same_td=True`: every batch is written into the same buffers instead of a fresh copy, which keeps
    large batches cheap; consume a batch before asking for the next one.
    """
    return Collector(
        env,
        policy,
        frames_per_batch=frames_per_batch,
        total_frames=total_frames,
        return_same_td=True,
        exploration_type=ExplorationType.RANDOM,
        auto_register_policy_transforms=False,  # the env already carries what the model needs
    )


def finished_episode_deliveries(batch: TensorDictBase) -> torch.Tensor:
    """float32 [n]: the deliveries of every episode that ended inside `batch` ([B, T] from a collector)."""
    done = batch["next", "done"].squeeze(-1)
    return batch["next", "episode_deliveries"].squeeze(-1)[done]


def collect_episodes(env: EnvBase, policy, max_steps: int) -> TensorDictBase:
    """One episode of every kitchen of `env` (which must start them together), as a [B, max_steps] batch."""
    num_envs = env.batch_size[0]
    collector = make_collector(env, policy, frames_per_batch=num_envs * max_steps, total_frames=num_envs * max_steps)
    try:
        batch = next(iter(collector)).clone()
    finally:
        collector.shutdown()
    return batch
