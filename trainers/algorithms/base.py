"""What an algorithm is to the PPO core of `trainers.ppo.loop`: an object with named hooks, each a no-op by default.

The core collects batches, computes GAE, runs the minibatch epochs of TorchRL's `ClipPPOLoss`, logs and
checkpoints; it knows no algorithm by name. An algorithm changes the loop only through these hooks, called in
this order (all but `process_minibatch`, which standardises the advantages, do nothing by default):

    set-up        check_config(config)    refuse settings the algorithm cannot train with (ConfigError; a classmethod,
                                          run by `check_algorithm` before anything is built); its own settings,
                                          the `algorithm_config` section, are a dataclass of its own (`Settings`,
                                          checked by its `check()`), read as `self.settings`
                  check()                 refuse a model the algorithm cannot train (ConfigError)
                  env_transforms()        transforms appended to the env after the model's own
                  acting_modules()        policy modules run after the actor while collecting
                  loss_actor()            the actor that ClipPPOLoss differentiates
                  configure_loss(loss)    e.g. a loss mask
                  parameters()            trained by the optimizer beside the loss module's
                  met_conventions(config) the scripted conventions it trains beside or imitates (recorded; a
                                          classmethod, so a run's partners can be asked before it is built)
    every update  process_batch(batch)            after GAE, before the epochs
                  process_minibatch(minibatch)    before the PPO loss of each minibatch (and before it is split
                                                  into shards, `minibatch_shards`)
                  auxiliary_losses(minibatch)     extra terms: "loss_*" entries join the total, others are logged
                  after_update()                  after the last optimizer step
    checkpoints   state_dict() / load_state_dict(state)   tensors and plain values only

`auxiliary_losses` entries are logged as "losses/<name without loss_>" or "charts/<name>", averaged over the
update's minibatches.

`process_batch` runs in the team's random stream, one team after another. With several teams in one process,
`process_minibatch`, `auxiliary_losses` and `after_update` of different teams run at once on threads
(`parallel_teams`), and a team alone runs `auxiliary_losses` of its minibatch's shards at once
(`minibatch_shards`, where the class says `shardable`): they must not draw from torch's global random generator
or change a process-wide mode.
"""

from __future__ import annotations

import dataclasses
from typing import ClassVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import Transform
from torchrl.objectives import ClipPPOLoss

from torch_kitchen.keys import ADVANTAGE
from torch_kitchen.models import ActorCritic
from torch_kitchen.partners.conventions import Convention
from trainers.config import ConfigError, TrainConfig, settings_from


def standardize_advantage(minibatch: TensorDictBase, where: torch.Tensor | None = None) -> None:
    """Standardises the advantages, as ClipPPOLoss's `normalize_advantage` does (the unbiased deviation, at least
    float resolution), with the mean and deviation of the transitions `where` is True ([..., 2], e.g. E3T's ego
    ones) or, by default, of all of them, pooled over kitchens, steps and agents. Done before the loss, the
    minibatch's shards share its statistics. Reads nothing back to the host; a single transition keeps scale 1."""
    advantage = minibatch.get(ADVANTAGE)
    if where is None:
        mean, deviation = advantage.mean(), advantage.std()
    else:
        weight = where.unsqueeze(-1).to(advantage.dtype)
        count = weight.sum()
        mean = (advantage * weight).sum() / count
        deviation = (((advantage - mean) ** 2 * weight).sum() / (count - 1)).sqrt()
    scale = deviation.nan_to_num(1.0, 1.0, 1.0).clamp_min(torch.finfo(torch.float).resolution)
    minibatch.set(ADVANTAGE, (advantage - mean) / scale)


@dataclasses.dataclass
class NoSettings:
    """The settings of an algorithm that has none of its own: its `algorithm_config` stays empty."""


class Algorithm:
    """Plain independent PPO (see the module docstring for the hooks and their order)."""

    # Its own settings, the config's `algorithm_config` section: a dataclass of `trainers.config.option` fields,
    # with a `check()` where some values cannot train (ConfigError naming `algorithm_config.<key>`).
    Settings: ClassVar[type] = NoSettings

    # The PPO loss and every auxiliary loss are plain means over the minibatch's transitions, so the mean of
    # equal shards' gradients is the minibatch's gradient (`minibatch_shards`).
    shardable = True
    # Where K teams learn at once on a GPU, `process_minibatch` and the loss of all K run as one computation under
    # `torch.vmap` (`torch_kitchen.teams.StackedLoss`), with the first team's hooks: they branch on no tensor's
    # value and keep no state of a team's own; an algorithm with parameters or losses of its own says False.
    stackable = True

    def __init__(self, config: TrainConfig, actor_critic: ActorCritic):
        self.config = config
        self.settings = self.settings_of(config)
        self.actor_critic = actor_critic

    @classmethod
    def settings_of(cls, config: TrainConfig):
        """Its `Settings` from the config's `algorithm_config` (the defaults where a key is not given), checked."""
        settings = settings_from(cls.Settings, config.algorithm_config, "algorithm_config.",
                                 f"algorithm={config.algorithm}")
        if hasattr(settings, "check"):
            settings.check()
        return settings

    @classmethod
    def check_config(cls, config: TrainConfig) -> None:
        """Refuses, with one line (ConfigError), settings of the whole config this algorithm cannot train with,
        before anything is built: here minibatch shards where the class is not `shardable` (its own settings are
        checked by `settings_of`)."""
        shards = config.runtime.minibatch_shards
        if shards > 1 and not cls.shardable:
            raise ConfigError(
                f"algorithm={config.algorithm} averages its losses over some of a minibatch's transitions, which "
                f"shards split unevenly: set runtime.minibatch_shards=1 (got {shards})"
            )

    # ---------------------------------------------------------------- set-up
    @classmethod
    def met_conventions(cls, config: TrainConfig) -> list[Convention]:
        """The scripted conventions a team of `config` trains beside or imitates: its run records their
        fingerprints, so that no evaluation scores it beside one of them as a held-out stranger and no resume
        trains it beside others."""
        return []

    def check(self) -> None:
        """Raises a ConfigError if the model cannot be trained by this algorithm."""

    def check_feed_forward(self, compared_with: str) -> None:
        """Refuses a recurrent model (ConfigError) where a loss compares the policy with `compared_with` at the
        batch's stored steps, for which a recurrent model has no hidden state."""
        if self.actor_critic.recurrent:
            raise ConfigError(f"algorithm={self.config.algorithm} compares the policy with {compared_with} at stored "
                              f"steps, which a recurrent model has no state for: choose a feed-forward architecture, "
                              f"not {self.config.architecture!r}")

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
        """Standardises the advantages (the loss does not): an override calls `super().process_minibatch` to keep
        that, or standardises them its own way, as E3T does over the ego's transitions."""
        standardize_advantage(minibatch)

    def auxiliary_losses(self, minibatch: TensorDictBase) -> dict[str, torch.Tensor]:
        return {}

    def after_update(self) -> None:
        pass

    # ---------------------------------------------------------------- checkpoints
    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass
