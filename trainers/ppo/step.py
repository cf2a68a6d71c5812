"""One PPO step, written once: a minibatch's losses and their gradient, each team's gradient made finite and
clipped to its own norm, and each team's Adam step.

The step moves K teams at once (K = 1 for a team learning alone): every loss output and gradient carries a leading
team dim. How the gradients are computed is handed in, so that the run options apply from outside the step
(`trainers.ppo.runtime`): a team's minibatch as it is (`team_gradients`), split into shards on threads, or K teams'
losses stacked as one computation; the step itself may be compiled, and on a GPU replayed as a CUDA graph.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING

import torch
from tensordict import TensorDictBase

if TYPE_CHECKING:
    from trainers.ppo.team import TrainingTeam

Losses = dict[str, torch.Tensor]
Gradients = list[torch.Tensor | None]  # per parameter of the teams, [K, *shape] (None: not taking part)
GradientsOf = Callable[[TensorDictBase], tuple[Losses, Gradients]]


def total_loss(losses: Losses) -> torch.Tensor:
    """The sum of the "loss_*" terms (TorchRL's convention: each already weighted by its coefficient)."""
    return sum(value for key, value in losses.items() if key.startswith("loss_"))


def ppo_step(teams: Sequence[TrainingTeam], gradients_of: GradientsOf, minibatch: TensorDictBase) -> Losses:
    """The PPO step of K teams on their minibatch (a team's, or K teams' stacked along a team dim): its losses and
    their gradients (`gradients_of`), each team's clipped (`clip_per_team`) and its Adam step. Returns the losses,
    [K] each, with the gradients' norms before clipping as "grad_norm". Reads nothing back from the device: whether
    the losses were finite is the update's to check, once at its end."""
    losses, gradients = gradients_of(minibatch)
    used = [index for index, gradient in enumerate(gradients) if gradient is not None]
    max_norm = teams[0].config.ppo.max_grad_norm
    clipped, losses["grad_norm"] = clip_per_team([gradients[index] for index in used], max_norm)
    gradients = list(gradients)
    for index, gradient in zip(used, clipped):
        gradients[index] = gradient
    for index, team in enumerate(teams):
        adam_step(team, [None if gradient is None else gradient[index] for gradient in gradients])
    return losses


def team_gradients(team: TrainingTeam, minibatch: TensorDictBase) -> tuple[Losses, Gradients]:
    """`ppo_step`'s losses and gradients for one team on its minibatch, made ready by the team's algorithm
    (`process_minibatch`); a team dim of 1 in front of each."""
    team.algorithm.process_minibatch(minibatch)
    losses, gradients = loss_gradients(team, minibatch)
    return ({key: value.unsqueeze(0) for key, value in losses.items()},
            [None if gradient is None else gradient.unsqueeze(0) for gradient in gradients])


def loss_gradients(team: TrainingTeam, minibatch: TensorDictBase) -> tuple[Losses, Gradients]:
    """The team's losses on a minibatch ready for them (TorchRL's loss and the algorithm's auxiliary ones) and the
    gradient of their total for each of its parameters (None where a parameter does not take part), laid out as
    backward() lays out a parameter's: its norm then sums in the same order."""
    losses = {**team.loss_module(minibatch), **team.algorithm.auxiliary_losses(minibatch)}
    gradients = torch.autograd.grad(total_loss(losses), team.parameters, allow_unused=True)
    laid_out = [None if gradient is None else laid_out_as(parameter, gradient)
                for parameter, gradient in zip(team.parameters, gradients)]
    return {key: value.detach() for key, value in losses.items()}, laid_out


def clip_per_team(gradients: list[torch.Tensor], max_norm: float) -> tuple[list[torch.Tensor], torch.Tensor]:
    """K teams' gradients, stacked along a leading team dim, as `clip_grad_norm_` leaves one team's: non-finite
    entries zeroed (a diverged minibatch must leave the weights finite until the update's end undoes it, since NaN
    weights would make the next minibatch's sampling fail, or assert on a GPU, before the check could say why), then
    each team's clipped to `max_norm` by their joint norm. Returns the clipped gradients, new tensors (in-place
    writes into autograd's outputs keep Inductor from replaying the step as a CUDA graph), and the K norms before
    clipping."""
    gradients = [gradient.nan_to_num(0.0, 0.0, 0.0) for gradient in gradients]
    norms = torch.stack([team_norms(gradient) for gradient in gradients]).norm(dim=0)
    scale = (max_norm / (norms + 1e-6)).clamp(max=1.0)
    return [gradient * scale.view(-1, *[1] * (gradient.dim() - 1)) for gradient in gradients], norms


def team_norms(gradient: torch.Tensor) -> torch.Tensor:
    """[K]: the norm of each team's entry of a gradient stacked along a leading team dim, read in memory order as
    `clip_grad_norm_` reads a gradient (a reshape would copy a column-major weight's gradient row by row, and sum
    in another order)."""
    if gradient.dim() == 1:  # a scalar parameter's
        return gradient.abs()
    return torch.linalg.vector_norm(gradient, dim=tuple(range(1, gradient.dim())))


def adam_step(team: TrainingTeam, gradients: Gradients) -> None:
    """The team's optimizer step on `gradients` (one per parameter), which are then let go."""
    for parameter, gradient in zip(team.parameters, gradients, strict=True):
        parameter.grad = None if gradient is None else laid_out_as(parameter, gradient)
    team.optimizer.step()
    for parameter in team.parameters:  # what `optimizer.zero_grad()` does, which compiled graphs stop at
        parameter.grad = None


def laid_out_as(parameter: torch.nn.Parameter, gradient: torch.Tensor) -> torch.Tensor:
    """`gradient` laid out in memory as `parameter` is: fused Adam reads a parameter and its gradient element by
    element in memory order (backward() would lay it out so too)."""
    return gradient if gradient.stride() == parameter.stride() else torch.empty_like(parameter).copy_(gradient)


def mean_over_shards(values: list[torch.Tensor]) -> torch.Tensor:
    return values[0] if len(values) == 1 else torch.stack(values).mean(0)
