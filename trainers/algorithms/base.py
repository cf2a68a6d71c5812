"""What an algorithm is to the PPO core of `trainers.ippo`: an object with named hooks, each a no-op by default.

The core collects batches, computes GAE, runs the minibatch epochs of TorchRL's `ClipPPOLoss`, logs and
checkpoints; it knows no algorithm by name. An algorithm changes the loop only through these hooks, called in
this order:

    set-up        check()                 refuse a model the algorithm cannot train (ConfigError)
                  env_transforms()        transforms appended to the env after the model's own
                  acting_modules()        policy modules run after the actor while collecting
                  loss_actor()            the actor that ClipPPOLoss differentiates
                  configure_loss(loss)    e.g. a loss mask or another advantage normalisation
                  parameters()            trained by the optimizer beside the loss module's
    every update  process_batch(batch)            after GAE, before the epochs
                  process_minibatch(minibatch)    before the PPO loss of each minibatch
                  auxiliary_losses(minibatch)     extra terms: "loss_*" entries join the total, others are logged
                  after_update()                  after the last optimizer step
    checkpoints   state_dict() / load_state_dict(state)   tensors and plain values only

`auxiliary_losses` entries are logged as "losses/<name without loss_>" or "charts/<name>", averaged over the
update's minibatches.

`process_batch` runs in the team's random stream, one team after another. With several teams in one process,
`process_minibatch`, `auxiliary_losses` and `after_update` of different teams run at once on threads
(`parallel_teams`): they must not draw from torch's global random generator or change a process-wide mode.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import Transform
from torchrl.objectives import ClipPPOLoss

from torch_kitchen.models import ActorCritic
from trainers.config import TrainConfig


class Algorithm:
    """Plain independent PPO: every hook does nothing (see the module docstring for the order of calls)."""

    def __init__(self, config: TrainConfig, actor_critic: ActorCritic):
        self.config = config
        self.actor_critic = actor_critic

    # ---------------------------------------------------------------- set-up
    def check(self) -> None:
        """Raises a ConfigError if the model cannot be trained by this algorithm."""

    def env_transforms(self) -> list[Transform]:
        return []

    def acting_modules(self) -> list[TensorDictModuleBase]:
        return []

    def loss_actor(self) -> TensorDictModuleBase:
        return self.actor_critic.actor

    def configure_loss(self, loss: ClipPPOLoss) -> None:
        pass

    def parameters(self) -> list[torch.nn.Parameter]:
        return []

    # ---------------------------------------------------------------- every update
    def process_batch(self, batch: TensorDictBase) -> None:
        pass

    def process_minibatch(self, minibatch: TensorDictBase) -> None:
        pass

    def auxiliary_losses(self, minibatch: TensorDictBase) -> dict[str, torch.Tensor]:
        return {}

    def after_update(self) -> None:
        pass

    # ---------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass
