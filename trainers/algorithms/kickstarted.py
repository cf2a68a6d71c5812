"""Kickstarted IPPO: IPPO with the scripted cook as a teacher all through training (Schmitt et al. 2018).

The loss adds `teacher_coef * H(cook, pi)`, the cross-entropy from the scripted cook's action distribution to the
policy's at every transition of the minibatch, the cook's read off the batch's own observations. Distillation
(`init_from: scripted_cook`) imitates the cook on a few hundred thousand states and stops; here every state
self-play visits is labelled, so the team keeps learning the cook's way of playing on kitchens where imitation
generalised least, while the reward mends what imitation gets wrong. The weight falls linearly to 0 over
`teacher_anneal_steps` env steps of this run (0: constant), after which the run is plain IPPO. The cook is the one
distillation learns from first (`distill.move_order`, or the seed's of `distill.teachers`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDictBase

from torch_kitchen.keys import OBSERVATION
from torch_kitchen.partners.conventions import Convention
from torch_kitchen.partners.scripted_cook import ScriptedCook
from trainers.algorithms.anchored import action_log_probs
from trainers.algorithms.ippo import IPPO
from trainers.config import ConfigError, TrainConfig, option


@dataclass
class KickstartedSettings:
    """Kickstarted IPPO's settings: `algorithm_config` of a config with `algorithm: kickstarted_ippo`."""

    teacher_coef: float = option(1.0, "weight of the cross-entropy from the scripted cook's policy to the team's")
    teacher_anneal_steps: int = option(0, "anneal teacher_coef linearly to 0 over this many env steps (0: constant)")

    def check(self) -> None:
        if not self.teacher_coef >= 0:
            raise ConfigError(f"algorithm_config.teacher_coef must be at least 0, got {self.teacher_coef}")
        if self.teacher_anneal_steps < 0:
            raise ConfigError(
                f"algorithm_config.teacher_anneal_steps must be at least 0, got {self.teacher_anneal_steps}")


TEACHER_PROBS = ("agents", "cook_probs")  # [..., 2, 6]: the scripted cook's action distribution, set per update


def teacher_weight(settings: KickstartedSettings, env_steps: int) -> float:
    """The teacher term's weight after `env_steps` of this run: `teacher_coef`, annealed linearly to 0."""
    if not settings.teacher_anneal_steps:
        return settings.teacher_coef
    return settings.teacher_coef * max(0.0, 1.0 - env_steps / settings.teacher_anneal_steps)


class KickstartedIPPO(IPPO):
    Settings = KickstartedSettings
    stackable = False  # a loss of its own, weighted by each team's own step count

    def __init__(self, config, actor_critic):
        super().__init__(config, actor_critic)
        self.teacher = ScriptedCook(config.distill_teacher())
        self.env_steps = 0  # of this run: the weight's schedule starts where the run does, after any init_from
        # A tensor filled in place, so that a compiled minibatch step reads the weight of the update it runs in.
        self.weight = torch.tensor(teacher_weight(self.settings, 0), device=config.runtime.device)

    def check(self) -> None:
        super().check()
        self.check_feed_forward("the cook")

    @classmethod
    def met_conventions(cls, config: TrainConfig) -> list[Convention]:
        return [config.distill_teacher()]

    def process_batch(self, batch: TensorDictBase) -> None:
        self.weight.fill_(teacher_weight(self.settings, self.env_steps))
        self.env_steps += batch.numel()
        with torch.no_grad():  # the cook's plan depends on the observation alone: once per update
            batch.set(TEACHER_PROBS, torch.softmax(self.teacher(batch.get(OBSERVATION)), dim=-1))

    def auxiliary_losses(self, minibatch: TensorDictBase) -> dict[str, torch.Tensor]:
        own = action_log_probs(self.actor_critic.actor, minibatch)
        probs = minibatch.get(TEACHER_PROBS)
        cross_entropy = -(probs * own).sum(-1).mean()
        agreement = (own.argmax(-1) == probs.argmax(-1)).float().mean()
        return {"loss_teacher": self.weight * cross_entropy, "teacher_cross_entropy": cross_entropy.detach(),
                "teacher_agreement": agreement, "teacher_weight": self.weight.clone()}

    def state_dict(self) -> dict:
        return {"env_steps": self.env_steps}

    def load_state_dict(self, state: dict) -> None:
        self.env_steps = state.get("env_steps", 0)
