"""The training reward and its generalised advantage estimates, without a Python loop over time.

GAE is the linear recurrence A_t = delta_t + c_t * A_{t+1} run backwards over the T steps of a batch, with
delta_t = r_t + gamma * (1 - terminated_t) * V_{t+1} - V_t and c_t = gamma * lambda * (1 - done_t). TorchRL's
functional `generalized_advantage_estimate` runs it one step at a time: T steps of a few kernels each, 1,280 kernel
launches for a 256-step batch. `reverse_linear_scan` runs it as a Hillis-Steele scan instead: after round k every
step holds its recurrence unrolled over the next 2^k steps, so ceil(log2 T) rounds of three element-wise
operations (8 rounds for T = 256) give every A_t at once, with no host synchronisation and static shapes (a
compiled graph or a CUDA graph takes it whole). Episodes that end mid-batch cut the recurrence through c_t = 0.
The sums run in another order than the sequential loop's, so the results agree with TorchRL's to float32 rounding
(`tests/trainers/test_advantages.py`). `compute_advantages` writes a batch's training reward (the sparse
reward plus the annealed shaping), advantages and value targets.
"""

from __future__ import annotations

import torch
from tensordict import TensorDictBase

from torch_kitchen.keys import ADVANTAGE, REWARD, SHAPED_REWARD, TRAIN_REWARD, VALUE, VALUE_TARGET
from trainers.config import TrainConfig


def _shifted(values: torch.Tensor, offset: int, dim: int) -> torch.Tensor:
    """values[t + offset] along `dim`, zero past the end."""
    ahead = values.narrow(dim, offset, values.shape[dim] - offset)
    padding = values.new_zeros(values.shape[:dim] + (offset,) + values.shape[dim + 1:])
    return torch.cat([ahead, padding], dim)


def reverse_linear_scan(inputs: torch.Tensor, coefficients: torch.Tensor, dim: int) -> torch.Tensor:
    """y with y_t = inputs_t + coefficients_t * y_{t+1} along `dim` (y past the end is 0), in ceil(log2 T) rounds.

    inputs, coefficients: float tensors of one shape; returns a tensor of that shape.
    """
    dim = dim % inputs.ndim
    total, factor = inputs, coefficients
    offset = 1
    while offset < inputs.shape[dim]:
        # Step t now reaches 2 * offset steps ahead: what step t + offset had gathered, weighted by the product of
        # the coefficients in between.
        total = total + factor * _shifted(total, offset, dim)
        factor = factor * _shifted(factor, offset, dim)
        offset *= 2
    return total


def generalized_advantages(
    gamma: float,
    lmbda: float,
    value: torch.Tensor,
    next_value: torch.Tensor,
    reward: torch.Tensor,
    done: torch.Tensor,
    terminated: torch.Tensor,
    time_dim: int,
) -> tuple[torch.Tensor, torch.Tensor]:
    """GAE advantages and value targets (advantage + value), as TorchRL's `generalized_advantage_estimate` gives
    them: every argument float (done and terminated bool) of one shape with time along `time_dim`; `done` cuts
    the recurrence (an episode ended), `terminated` also drops the bootstrap from `next_value`."""
    delta = reward + gamma * (~terminated).to(value.dtype) * next_value - value
    advantage = reverse_linear_scan(delta, gamma * lmbda * (~done).to(value.dtype), time_dim)
    return advantage, advantage + value


def shaping_weight_at(config: TrainConfig, env_steps: int) -> float:
    """The weight of the shaped reward in the training reward after `env_steps`: annealed linearly to 0 over
    `shaping_anneal_steps` (0: constant)."""
    if config.ppo.shaping_anneal_steps <= 0:
        return config.ppo.shaping_weight
    return config.ppo.shaping_weight * max(0.0, 1.0 - env_steps / config.ppo.shaping_anneal_steps)


def compute_advantages(batch: TensorDictBase, critic, config: TrainConfig, shaping_weight: float) -> None:
    """Writes the training reward (`TRAIN_REWARD`: sparse + `shaping_weight` x shaped), GAE advantages and value
    targets into `batch` ([B, T], agents [B, T, 2]); the env's own rewards stay as they were.

    Values come from the collection pass (the policy runs the critic), so recurrent critics see the hidden
    state they had while acting; only the step after the batch needs a new critic call. The time limit ends
    an episode as a terminal state, as in the paper's JaxMARL code: no bootstrap across it.
    """
    reward = batch.get(("next", *REWARD)) + shaping_weight * batch.get(("next", *SHAPED_REWARD))
    batch.set(("next", *TRAIN_REWARD), reward)
    done = batch.get(("next", "done")).unsqueeze(-2).expand_as(reward)  # [B, T, 1] -> [B, T, 2, 1]
    value = batch.get(VALUE)
    with torch.no_grad():
        after = critic(batch["next"][:, -1].clone()).get(VALUE)
    next_value = torch.cat([value[:, 1:], after.unsqueeze(1)], dim=1)
    advantage, target = generalized_advantages(
        config.ppo.gamma, config.ppo.gae_lambda, value, next_value, reward, done, done, time_dim=1
    )
    batch.set(ADVANTAGE, advantage)
    batch.set(VALUE_TARGET, target)
