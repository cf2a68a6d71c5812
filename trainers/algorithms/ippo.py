"""IPPO: both agents learn from their own transitions with independent PPO (with `share_params`, one network).

Everything IPPO needs is the PPO core itself; this class only refuses models built for another algorithm.
"""

from __future__ import annotations

from torch_kitchen.models.partner_predictor import partner_context_length
from trainers.algorithms.base import Algorithm
from trainers.config import ConfigError


class IPPO(Algorithm):
    def check(self) -> None:
        if partner_context_length(self.actor_critic.actor):
            raise ConfigError(
                f"{self.config.architecture!r} carries E3T's partner predictor, which only algorithm=e3t trains: set "
                "algorithm=e3t, or choose an architecture without it (mlp, gnn, ...)"
            )
