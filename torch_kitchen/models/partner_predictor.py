"""E3T's partner model (`PartnerPredictor`): the partner context -> the partner's next action, before the actor's
torso in the "e3t_mlp" and "e3t_gnn" architectures.
"""

from __future__ import annotations

import functools

import torch
from tensordict import TensorDictBase
from tensordict.nn import (
    TensorDictModuleBase,
    TensorDictSequential,
)
from torch import nn
from torchrl.modules import ProbabilisticActor

from jax_env import NUM_ACTIONS
from torch_kitchen.keys import (
    OBSERVATION,
    PARTNER_LOGITS,
    PARTNER_PREDICTION,
)
from torch_kitchen.models.acting import sampling_actor
from torch_kitchen.models.e3t_partner import CONTEXT_ACTION, CONTEXT_OBSERVATION, NO_ACTION
from torch_kitchen.models.networks import (
    ObservationEncoder,
    _hidden_linear,
    _orthogonal_,
)
from torch_kitchen.torchrl_internals import MultiAgentNet

E3T_CONTEXT = 5  # (observation, partner action) pairs the partner predictor reads


def make_predictor_head(hidden: int, length: int) -> nn.Sequential:
    """One agent's reading of its context: float [..., k, h + 7] (each observation's code, then the one-hot partner
    action: 6 actions and NO_ACTION) -> float [..., 6] logits, through Linear(h) + ReLU -> Linear(6)."""
    return nn.Sequential(
        nn.Flatten(-2),
        _hidden_linear(length * (hidden + NO_ACTION + 1), hidden), nn.ReLU(),
        _orthogonal_(nn.Linear(hidden, NUM_ACTIONS), 0.01),
    )


class PartnerPredictor(TensorDictModuleBase):
    """E3T's partner model over both agents: the partner context -> the partner's next action.

    in:  ("agents", "context_observation") uint8 [*B, 2, k, H, W, C], ("agents", "context_action") int64 [*B, 2, k]
    out: ("agents", "partner_logits") [*B, 2, 6] and ("agents", "partner_prediction"), their softmax, detached:
         the policy reads the prediction as an input and the predictor learns from its own cross-entropy only.
    Each context observation goes through an encoder of the policy's kind ("mlp" or "gnn", weights of its own);
    the head reads the k codes with the k actions. `sequence_logits` gives the same logits for whole
    trajectories while encoding each observation once instead of k times (training).
    """

    def __init__(self, encoder: str, obs_shape: tuple[int, int, int], hidden: int, share_params: bool,
                 length: int = E3T_CONTEXT):
        super().__init__()
        self.length = length
        self.encoder = ObservationEncoder(encoder, obs_shape, hidden, share_params)
        self.head = MultiAgentNet(functools.partial(make_predictor_head, hidden, length),
                                  (length, hidden + NO_ACTION + 1), share_params=share_params)
        self.in_keys = [CONTEXT_OBSERVATION, CONTEXT_ACTION]
        self.out_keys = [PARTNER_LOGITS, PARTNER_PREDICTION]

    def _read(self, codes: torch.Tensor, actions: torch.Tensor) -> torch.Tensor:
        """codes float [*B, 2, k, h], actions int64 [*B, 2, k] -> logits [*B, 2, 6]."""
        one_hot = nn.functional.one_hot(actions, NO_ACTION + 1).to(codes.dtype)
        return self.head(torch.cat([codes, one_hot], -1))

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        # The encoder wants the agent dim just before the observation: [*B, 2, k, ...] -> [*B, k, 2, ...].
        codes = self.encoder(tensordict.get(CONTEXT_OBSERVATION).movedim(-5, -4)).movedim(-3, -2)
        logits = self._read(codes, tensordict.get(CONTEXT_ACTION))
        tensordict.set(PARTNER_LOGITS, logits)
        tensordict.set(PARTNER_PREDICTION, torch.softmax(logits.detach(), -1))
        return tensordict

    def sequence_logits(self, batch: TensorDictBase) -> torch.Tensor:
        """Logits [B, T, 2, 6] over trajectories [B, T] as a collector gives them (consecutive steps per kitchen).

        Slot j of step t's context holds the observation of step t - k + j, or padding where that step lies
        before the episode's start (there its action is NO_ACTION). So the codes of the batch's own
        observations, after the codes of the context at t = 0 (the steps before the batch), give every
        context by a sliding window; padded slots take the code of an all-zero observation, as they do step by
        step. Equal to `forward` step by step (tested), with one encoding per observation.
        """
        context_obs, actions = batch.get(CONTEXT_OBSERVATION), batch.get(CONTEXT_ACTION)  # [B, T, 2, k, ...]
        observation = batch.get(OBSERVATION)  # [B, T, 2, H, W, C]
        steps = observation.shape[1]
        before = self.encoder(context_obs[:, 0].movedim(-5, -4))  # [B, k, 2, h]: steps -k .. -1
        codes = torch.cat([before, self.encoder(observation)], dim=1)  # [B, k + T, 2, h]
        windows = codes.unfold(1, self.length, 1)[:, :steps].transpose(-1, -2)  # [B, T, 2, k, h]
        padding = self.encoder(torch.zeros_like(observation[:1, 0]))  # [1, 2, h]
        padded = (actions == NO_ACTION).unsqueeze(-1)
        windows = torch.where(padded, padding.unsqueeze(-2), windows)
        return self._read(windows, actions)


def partner_context_length(network: nn.Module) -> int:
    """The context length k a network's partner predictor reads (0 without one)."""
    lengths = {module.length for module in network.modules() if isinstance(module, PartnerPredictor)}
    if len(lengths) > 1:
        raise ValueError(f"one network reads partner contexts of several lengths {sorted(lengths)}")
    return lengths.pop() if lengths else 0


def split_partner_predictor(actor: ProbabilisticActor) -> tuple[PartnerPredictor, ProbabilisticActor]:
    """An E3T actor, `sampling_actor(TensorDictSequential(predictor, policy))` as `build_e3t` makes it, as its
    `PartnerPredictor` and the sampling actor of `policy` alone, which reads the ("agents", "partner_prediction")
    already in a tensordict (the one stored while acting) instead of predicting it anew. Shares their weights.

    Raises ValueError for an actor of another form (e.g. one without a predictor).
    """
    body = actor.module[0] if len(actor.module) else None
    parts = list(body.module) if isinstance(body, TensorDictSequential) else []
    if len(parts) < 2 or not isinstance(parts[0], PartnerPredictor):
        raise ValueError(
            "E3T needs an actor of the form sampling_actor(TensorDictSequential(PartnerPredictor(...), policy)), "
            "as the architectures e3t_mlp and e3t_gnn build it"
        )
    return parts[0], sampling_actor(TensorDictSequential(*parts[1:]))
