"""Anchored IPPO: IPPO with a KL penalty that keeps the policy near the one it started from (`init_from`).

The loss adds `anchor_coef * KL(pi || pi_start)` at every transition of the minibatch, pi_start the policy as it
was before the first update. Started from a behaviour-cloned proxy, this is human-regularised RL (as in piKL,
Jacob et al. 2022): the reward mends what cloning alone gets stuck in, while the KL term keeps the humans' way of
playing; `kitchen-humans train` fine-tunes the proxies that way where two cloned proxies deliver far less than the
humans did. The starting policy is saved with the run's checkpoints, so a resumed run keeps its anchor.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass

import torch
from tensordict import TensorDictBase

from trainers.algorithms.ippo import IPPO
from trainers.config import ConfigError, TrainConfig, option


@dataclass
class AnchoredSettings:
    """Anchored IPPO's settings: `algorithm_config` of a config with `algorithm: anchored_ippo`."""

    anchor_coef: float = option(0.1, "weight of KL(policy || starting policy) in the loss")

    def check(self) -> None:
        if not self.anchor_coef >= 0:
            raise ConfigError(f"algorithm_config.anchor_coef must be at least 0, got {self.anchor_coef}")


ANCHOR_LOG_PROBS = ("agents", "anchor_log_probs")  # [..., 2, 6]: the starting policy's, set once per update


def action_log_probs(actor, batch: TensorDictBase) -> torch.Tensor:
    """The actor's log-probabilities of every action [..., 2, 6] at the batch's observations (no action sampled, so
    no random draw)."""
    return torch.log_softmax(actor.get_dist(batch.select(*actor.in_keys, strict=False).clone(False)).logits, -1)


def policy_kl(policy, anchor_log_probs: torch.Tensor, minibatch: TensorDictBase) -> torch.Tensor:
    """KL(policy || anchor) at each transition of `minibatch` [..., 2], averaged, given the anchor's log-probabilities
    there. From log-probabilities, so an action the anchor all but rules out costs a finite amount (torch's
    `kl_divergence` says inf where its probability underflows to 0)."""
    own = action_log_probs(policy, minibatch)
    return (own.exp() * (own - anchor_log_probs)).sum(-1).mean()


class AnchoredIPPO(IPPO):
    Settings = AnchoredSettings
    stackable = False  # the anchor is each team's own

    @classmethod
    def check_config(cls, config: TrainConfig) -> None:
        super().check_config(config)
        if not config.init_from:
            raise ConfigError("algorithm=anchored_ippo keeps the policy near the one it starts from: set init_from "
                              "(a run directory, e.g. runs/bc_forced_coord/seed0, or scripted_cook)")

    def __init__(self, config: TrainConfig, actor_critic):
        super().__init__(config, actor_critic)
        self.anchor = None  # the policy before the first update (its `init_from` weights), taken then

    def check(self) -> None:
        super().check()
        self.check_feed_forward("its start")

    def process_batch(self, batch: TensorDictBase) -> None:
        if self.anchor is None:
            self.anchor = copy.deepcopy(self.actor_critic.actor).requires_grad_(False)
        with torch.no_grad():  # the anchor does not change: once per update, not at every epoch's minibatch
            batch.set(ANCHOR_LOG_PROBS, action_log_probs(self.anchor, batch))

    def auxiliary_losses(self, minibatch: TensorDictBase) -> dict[str, torch.Tensor]:
        kl = policy_kl(self.actor_critic.actor, minibatch.get(ANCHOR_LOG_PROBS), minibatch)
        return {"loss_anchor": self.settings.anchor_coef * kl, "anchor_kl": kl.detach()}

    def state_dict(self) -> dict:
        return {} if self.anchor is None else {"anchor": self.anchor.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        if "anchor" in state:
            self.anchor = copy.deepcopy(self.actor_critic.actor).requires_grad_(False)
            self.anchor.load_state_dict(state["anchor"])
