"""How the models act: one distribution over the actions (`ActionDistribution`), which TorchRL's
`ProbabilisticActor` samples (`sampling_actor`), and so does `ActingPass`, a feed-forward actor and critic in one
pass over plain tensors for collection (`sample_actions`).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from tensordict import TensorDictBase
from tensordict.nn import (
    InteractionType,
    TensorDictModuleBase,
    TensorDictSequential,
)
from tensordict.nn.probabilistic import interaction_type
from torch import nn
from torchrl.modules import ProbabilisticActor

from jax_env import NUM_ACTIONS
from torch_kitchen.keys import (
    ACTION,
    LOG_PROB,
    LOGITS,
    OBSERVATION,
    VALUE,
)
from torch_kitchen.torchrl_internals import MultiAgentNet


def sampling_actor(policy: TensorDictModuleBase) -> ProbabilisticActor:
    """A `ProbabilisticActor` sampling ("agents", "action") and its log-prob from `policy`'s ("agents", "logits")."""
    return ProbabilisticActor(
        policy,
        in_keys={"logits": LOGITS},
        out_keys=[ACTION],
        distribution_class=ActionDistribution,
        return_log_prob=True,
        log_prob_key=LOG_PROB,
        # The protocol samples actions in training and in evaluation alike.
        default_interaction_type=InteractionType.RANDOM,
    )


def layers_of(network: nn.Module) -> list[nn.Module]:
    """The layers of a chain of (nested) `nn.Sequential`s, in order."""
    if isinstance(network, nn.Sequential):
        return [layer for part in network for layer in layers_of(part)]
    return [network]


class ActingPass(TensorDictModuleBase):
    """A feed-forward actor and critic in one pass over plain tensors: what `TensorDictSequential(actor, critic)`
    writes (logits, sampled action, its log-prob, value), bit for bit, without the TensorDict plumbing around
    each of their modules. Collection runs the policy at every step, where that plumbing costs several times
    the arithmetic of small networks. Holds the actor's and critic's own networks: their weights, not copies.

    policy_net / value_net: uint8 observations [*B, 2, H, W, C] -> logits [*B, 2, 6] / values [*B, 2, 1].
    """

    def __init__(self, policy_net: nn.Module, value_net: nn.Module):
        super().__init__()
        self.policy_net, self.value_net = policy_net, value_net
        self.in_keys = [OBSERVATION]
        self.out_keys = [LOGITS, ACTION, LOG_PROB, VALUE]

    def forward(self, tensordict: TensorDictBase) -> TensorDictBase:
        for key, value in zip(self.out_keys, self.act(tensordict.get(OBSERVATION))):
            tensordict.set(key, value)
        return tensordict

    def act(self, observation: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The pass on plain tensors: observation uint8 [*B, 2, H, W, C] -> (logits [*B, 2, 6], action int64 [*B, 2],
        its log-prob [*B, 2], value [*B, 2, 1]), in `out_keys`' order."""
        logits = self.policy_net(observation)
        action, log_prob = sample_actions(logits)
        return logits, action, log_prob, self.value_net(observation)

    def shared_networks(self) -> tuple[nn.Sequential, nn.Sequential] | None:
        """The policy and value networks as chains of plain modules holding these weights (not copies), where both
        share their parameters between the agents; else None."""
        if not all(isinstance(part, MultiAgentNet) and part.share_params
                   for network in (self.policy_net, self.value_net) for part in network):
            return None
        return tuple(nn.Sequential(*(part.shared_net() for part in network))
                     for network in (self.policy_net, self.value_net))


class ActionDistribution(torch.distributions.Categorical):
    """The policies' distribution over the six actions, from their logits [*B, 6]: torch's Categorical, its
    arguments unchecked (validating them reads the logits back on the host at every call; NaN losses are caught
    once per update). TorchRL's actor samples from it (`sampling_actor`), and so do the acting pass and the
    stacked teams (`sample_actions`)."""

    def __init__(self, logits: torch.Tensor, validate_args: bool = False):
        super().__init__(logits=logits, validate_args=validate_args)

    @property
    def probs(self) -> torch.Tensor:
        """The probabilities as exp of the normalised logits (the log-probabilities): what torch's softmax gives, to
        float32 rounding, at half the cost of a loss's forward and backward, since torch's CPU softmax is slow over
        rows of six."""
        return self.logits.exp()


def draw_categorical(probs: torch.Tensor) -> torch.Tensor:
    """One draw per row of probs float [N, 6] from torch's current random stream: int64 [N, 1], as
    `torch.distributions.Categorical.sample` draws."""
    return torch.multinomial(probs, 1, True)


def sample_actions(logits: torch.Tensor, draw: Callable[[torch.Tensor], torch.Tensor] = draw_categorical
                   ) -> tuple[torch.Tensor, torch.Tensor]:
    """Actions int64 [*B] and their log-probabilities float32 [*B] from logits [*B, 6], from the actor's
    `ActionDistribution`: sampled by `draw` (interaction type RANDOM, the default; stacked teams draw each from
    its own random stream), or the most likely (DETERMINISTIC or MODE)."""
    distribution = ActionDistribution(logits)
    mode = interaction_type() or InteractionType.RANDOM  # the actor's default: sample
    if mode is InteractionType.RANDOM:
        action = draw(distribution.probs.reshape(-1, NUM_ACTIONS)).reshape(logits.shape[:-1])
    elif mode in (InteractionType.DETERMINISTIC, InteractionType.MODE):
        action = distribution.mode
    else:
        raise ValueError(f"a categorical policy has no {mode.name.lower()} action; sample or take its mode")
    return action, distribution.log_prob(action)


def plain_network(network: TensorDictSequential) -> nn.Sequential:
    """The modules of a chain of TensorDict modules (each reading what the one before wrote) as plain torch."""
    return nn.Sequential(*(module.module for module in network.module))
