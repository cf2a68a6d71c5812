"""Where a team's networks run and how its optimizer is set up for the run's options: below the training team that
builds them and the runtime that steps them (`trainers.ppo.runtime`), so imports run one way."""

from __future__ import annotations

from typing import TYPE_CHECKING

import torch

from torch_kitchen.cpu_kernels import accelerate_cpu
from trainers.config import TrainConfig

if TYPE_CHECKING:
    from torch_kitchen.models import ActorCritic


def place_networks(config: TrainConfig, actor_critic: ActorCritic, own_kernels: bool) -> None:
    """The team's networks on the run's device; on a CPU with `own_kernels` (networks built from the config, not a
    user's own) their layers swapped for this project's faster CPU kernels (`accelerate_cpu`)."""
    if own_kernels and torch.device(config.runtime.device).type == "cpu":
        accelerate_cpu(actor_critic.actor, actor_critic.critic)
    actor_critic.actor.to(config.runtime.device)
    actor_critic.critic.to(config.runtime.device)


def make_optimizer(config: TrainConfig, parameters: list[torch.nn.Parameter]) -> torch.optim.Adam:
    """The team's Adam: with `compile_update` its learning rate a tensor, so that annealing it changes a value
    rather than the compiled graph, and on a GPU its step counts on the device, as a CUDA graph needs; else fused,
    one kernel for all parameters instead of a few per tensor (3x faster on a CPU at hidden 256)."""
    if config.runtime.compile_update:
        lr = torch.tensor(config.ppo.lr, device=config.runtime.device)
        return torch.optim.Adam(parameters, lr=lr, eps=config.ppo.adam_eps, capturable=config.runtime.on_gpu)
    return torch.optim.Adam(parameters, lr=config.ppo.lr, eps=config.ppo.adam_eps, fused=True)


def set_learning_rate(config: TrainConfig, optimizer: torch.optim.Optimizer, lr: float) -> None:
    """The optimizer's learning rate for the next update: with `compile_update` written into the tensor the
    compiled step reads (made again after resuming a run saved without it)."""
    for group in optimizer.param_groups:
        if config.runtime.compile_update:
            if not isinstance(group["lr"], torch.Tensor):
                group["lr"] = torch.tensor(lr, device=config.runtime.device)
            group["lr"].fill_(lr)
        else:
            group["lr"] = lr
