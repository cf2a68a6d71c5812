"""E3T (Yan et al., 2023): a mixed partner in every episode, PPO on the ego's transitions, a partner predictor.

In every episode one agent per kitchen, drawn by `PartnerSeats`, is the mixed partner: it acts from
(1 - eps) * pi + eps * uniform (`PartnerMixture`), pi the ego's own policy or, with `partner_policy: copy`, a
slow copy of it that follows the ego by `partner_copy_rate` after every update. PPO learns from the ego's
transitions only (TorchRL's `loss_mask_key`), with advantages standardised over those (`standardize_advantage`).
The actor's `PartnerPredictor` (models e3t_mlp, e3t_gnn) is trained by cross-entropy against the partner's actual
actions; the PPO loss differentiates the policy without it, reading the prediction stored while acting, so its
probability ratios compare the policy on the very inputs it acted on.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs import Transform
from torchrl.objectives import ClipPPOLoss

from torch_kitchen.keys import ACTION
from torch_kitchen.models import ActorCritic
from torch_kitchen.models.e3t_partner import MIXED, PartnerMixture, PartnerSeats
from torch_kitchen.models.partner_predictor import split_partner_predictor
from trainers.algorithms.base import Algorithm, standardize_advantage
from trainers.config import ConfigError, TrainConfig, option

EGO = ("agents", "ego")  # bool [B, T, 2]: the transitions PPO learns from
PARTNER_POLICIES = ("ego", "copy")  # pi of the mixed partner: the policy itself, or a slow copy of it


def partner_prediction_loss(predictor, minibatch: TensorDictBase) -> tuple[torch.Tensor, torch.Tensor]:
    """Cross-entropy of every agent's predicted partner action against the action the partner took at that step,
    and the accuracy of the most likely one, over whole kitchen sequences [mb, T]. The predictor reads only the
    context of earlier steps."""
    logits = predictor.sequence_logits(minibatch)  # [mb, T, 2, 6]
    partner_action = minibatch.get(ACTION).flip(-1)
    loss = torch.nn.functional.cross_entropy(logits.flatten(0, -2), partner_action.flatten())
    accuracy = (logits.argmax(-1) == partner_action).float().mean()
    return loss, accuracy.detach()


@dataclass
class E3TSettings:
    """E3T's settings: `algorithm_config` of a config with `algorithm: e3t`."""

    partner_epsilon: float = option(0.3, "the mixed partner acts from (1 - eps) * pi + eps * uniform")
    partner_policy: str = option("ego", 'pi of the mixed partner: "ego" (the policy itself) or "copy" (a slow copy)')
    partner_copy_rate: float = option(0.01, '"copy": after every update, copy += rate * (ego - copy)')
    predictor_coef: float = option(1.0, "weight of the partner predictor's cross-entropy in the loss")

    def check(self) -> None:
        if self.partner_policy not in PARTNER_POLICIES:
            raise ConfigError(f"algorithm_config.partner_policy must be one of {', '.join(PARTNER_POLICIES)}, "
                              f"got {self.partner_policy!r}")
        for name in ("partner_epsilon", "partner_copy_rate"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"algorithm_config.{name} must lie in [0, 1], got {getattr(self, name)}")
        if not self.predictor_coef >= 0:
            raise ConfigError(f"algorithm_config.predictor_coef must be at least 0, got {self.predictor_coef}")


class E3T(Algorithm):
    Settings = E3TSettings
    # Its PPO terms average over the ego's transitions only, which equal shards of a minibatch split unevenly.
    shardable = False
    stackable = False  # its partner predictor and the seats are each team's own

    def __init__(self, config: TrainConfig, actor_critic: ActorCritic):
        super().__init__(config, actor_critic)
        try:
            self.predictor, self.policy = split_partner_predictor(actor_critic.actor)
        except ValueError:
            raise ConfigError(
                f"algorithm=e3t needs a model with a partner predictor, and {config.architecture!r} has none: use "
                "architecture=e3t_mlp or e3t_gnn (configs/e3t/)"
            ) from None
        self.seats = PartnerSeats(config.seed)
        # The slow copy acts for the mixed partner with `partner_policy: copy`; None: the ego's own policy.
        self.partner = None
        if self.settings.partner_policy == "copy":
            self.partner = copy.deepcopy(actor_critic.actor).requires_grad_(False)

    def env_transforms(self) -> list[Transform]:
        return [self.seats]

    def acting_modules(self) -> list[TensorDictModuleBase]:
        return [PartnerMixture(self.settings.partner_epsilon, self.partner)]

    def loss_actor(self) -> TensorDictModuleBase:
        return self.policy

    def configure_loss(self, loss: ClipPPOLoss) -> None:
        loss.loss_mask_key = EGO

    def parameters(self) -> list[torch.nn.Parameter]:
        return list(self.predictor.parameters())

    def process_batch(self, batch: TensorDictBase) -> None:
        batch.set(EGO, ~batch.get(MIXED))

    def process_minibatch(self, minibatch: TensorDictBase) -> None:
        standardize_advantage(minibatch, where=minibatch.get(EGO))  # the mixed partner's would skew them

    def auxiliary_losses(self, minibatch: TensorDictBase) -> dict[str, torch.Tensor]:
        loss, accuracy = partner_prediction_loss(self.predictor, minibatch)
        return {"loss_partner_prediction": self.settings.predictor_coef * loss, "partner_accuracy": accuracy}

    def after_update(self) -> None:
        if self.partner is not None:
            with torch.no_grad():
                for slow, ego in zip(self.partner.parameters(), self.actor_critic.actor.parameters()):
                    slow.lerp_(ego, self.settings.partner_copy_rate)

    def state_dict(self) -> dict:
        state = {"partner_seats": self.seats.state_dict()}
        if self.partner is not None:
            state["partner_copy"] = self.partner.state_dict()
        return state

    def load_state_dict(self, state: dict) -> None:
        self.seats.load_state_dict(state["partner_seats"])
        if self.partner is not None:
            self.partner.load_state_dict(state["partner_copy"])
