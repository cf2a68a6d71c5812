"""How the teams of one batch act and learn on this machine: the run options (`threads`, `parallel_teams`,
`minibatch_shards`, `compile_policy`, `compile_update`, the device), which change how fast a run goes and never
what it learns. The PPO loop (`trainers.ppo`) hands each team's update to an `UpdateRunner`; it runs them one
after another, on threads at once, or (on a GPU) as one stacked computation, and each team's minibatch step as it
is, split into shards on threads, or compiled.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase
from torchrl.envs.utils import set_exploration_type
from torchrl.modules import set_recurrent_mode

from torch_kitchen.teams import StackedLoss, TeamPolicy, stackable_acting
from trainers.algorithms import ALGORITHMS
from trainers.config import TrainConfig
from trainers.machine import usable_cores
from trainers.resume import TrainingDiverged
from trainers.rollout import select_kitchens
from trainers.training_run import (
    RestorePoint,
    TrainingRun,
    apply_gradients,
    gradient_for,
    mean_over_shards,
    shard_gradients,
    total_loss,
)

Learn = Callable  # trainers.ppo.learn: (team, batch, orders, minibatch step) -> the update's metrics
Finish = Callable  # trainers.ppo.finish_update: (team, batch, minibatch losses, restore point) -> its metrics


def use_threads(config: TrainConfig) -> None:
    """Torch's CPU threads for this process (`threads`), set before anything is built."""
    torch.set_num_threads(config.runtime.threads)


def minibatch_shards(config: TrainConfig) -> int:
    """The parts a team's minibatch is split into (`minibatch_shards`, or where it is 0 the number that pays: two
    threads' worth of arithmetic in a minibatch costs more than a second pass of the loss's Python on a CPU from
    hidden 128 up: 1.2-1.4x the steps/s at 32 x 256, 0.8x at hidden 64, 16 x 128; BENCHMARKS.md). It depends on
    the config alone, so a team gets the same numbers alone and beside other teams."""
    if config.runtime.minibatch_shards:
        return config.runtime.minibatch_shards
    if config.runtime.compile_update:  # one compiled step per minibatch
        return 1
    pays = (torch.device(config.runtime.device).type == "cpu" and config.hidden >= 128
            and config.kitchens_per_minibatch % 2 == 0 and ALGORITHMS[config.algorithm].shardable)
    return 2 if pays else 1


def acting_policy(config: TrainConfig, teams: Sequence[TrainingRun]) -> TeamPolicy:
    """The teams' policies acting on their rows of the batch, each in its random stream: on a GPU as one stacked
    network where they allow it (compiled, replayed as CUDA graphs), on a CPU one after another; each compiled
    with `compile_policy`."""
    policies = [team.policy for team in teams]
    streams = [team.stream for team in teams]
    stack = acts_stacked(config, policies)
    compile_mode = ("reduce-overhead" if stack else "default") if config.runtime.compile_policy else None
    return TeamPolicy(policies, streams, config.num_envs, stack, compile_mode)


def compile_step(step: Callable[[TensorDictBase], dict[str, torch.Tensor]],
                 device: str | torch.device) -> Callable[[TensorDictBase], dict[str, torch.Tensor]]:
    """A minibatch step (`ppo_step`, `stacked_step`) compiled (`compile_update`). On a GPU in "reduce-overhead"
    mode, which replays the compiled graphs as CUDA graphs (a minibatch's launches at once); their outputs live in
    buffers that the next replay overwrites, and the update keeps every minibatch's losses, so these are copied
    out, all in one tensor."""
    compiled = torch.compile(step, mode="reduce-overhead" if torch.device(device).type == "cuda" else None)

    def run(minibatch: TensorDictBase) -> dict[str, torch.Tensor]:
        torch.compiler.cudagraph_mark_step_begin()
        losses = compiled(minibatch)
        copied = torch.cat([value.detach().reshape(-1) for value in losses.values()])
        parts = copied.split([value.numel() for value in losses.values()])
        return {key: part.view_as(value) for (key, value), part in zip(losses.items(), parts)}

    return run


def acts_stacked(config: TrainConfig, policies: Sequence[TensorDictModuleBase]) -> bool:
    """Whether the teams act as one stacked network (`TeamPolicy`'s `stack`): on a GPU, where the policies allow
    it, a team's kernel launches for all of them; on a CPU they act one after another, each with its sparse first
    layer."""
    return config.runtime.on_gpu and stackable_acting(policies) is not None


def learns_stacked(config: TrainConfig, teams: Sequence[TrainingRun]) -> bool:
    """Whether the teams' minibatch steps run as one (`stacked_update`): on a GPU, where several teams learn and
    their model and algorithm allow it (feed-forward with shared parameters, `Algorithm.stackable`); on a CPU each
    team learns on its own, with its sparse first layer, on threads where `parallel_teams`."""
    stackable = (config.share_params and not teams[0].actor_critic.recurrent and teams[0].algorithm.stackable
                 and minibatch_shards(config) == 1)
    return config.runtime.on_gpu and len(teams) > 1 and stackable


def stacked_update(teams: Sequence[TrainingRun]) -> Callable[[TensorDictBase], dict[str, torch.Tensor]]:
    """The teams' minibatch step as one computation: `stacked_step` over their `StackedLoss`, compiled with
    `compile_update` (on a GPU, replayed as CUDA graphs)."""
    loss = StackedLoss([team.loss_module for team in teams], teams[0].algorithm.process_minibatch)
    step = functools.partial(stacked_step, teams, loss)
    return compile_step(step, teams[0].config.runtime.device) if teams[0].config.runtime.compile_update else step


def minibatch_step(team: TrainingRun, minibatch: TensorDictBase,
                   pool: ThreadPoolExecutor | None) -> dict[str, torch.Tensor]:
    """One PPO step on a minibatch: the mean of its shards' losses and gradients (`minibatch_shards` equal parts
    by kitchen, on `pool`'s threads at once where given; one after the other gives the same numbers), clipped
    and applied; returns the losses. Reads nothing back from the device: whether the losses were finite is the
    caller's to check (`learn`, once per update)."""
    if team.compiled_step is not None:
        return team.compiled_step(minibatch)
    if minibatch_shards(team.config) == 1:
        return ppo_step(team, minibatch)
    shards = minibatch.chunk(minibatch_shards(team.config), dim=0)
    run = pool.map if pool is not None and len(shards) > 1 else map
    shard_losses, gradients_by_shard = zip(*run(functools.partial(shard_gradients, team), shards))
    losses = {key: mean_over_shards([losses[key] for losses in shard_losses]) for key in shard_losses[0]}
    for parameter, gradients in zip(team.parameters, zip(*gradients_by_shard)):
        parameter.grad = gradient_for(parameter, list(gradients))
    losses["grad_norm"] = apply_gradients(team)
    return losses


def ppo_step(team: TrainingRun, minibatch: TensorDictBase) -> dict[str, torch.Tensor]:
    """The PPO step of one team on a minibatch, written once: the loss, its backward, the clipping and the Adam step,
    with nothing read back on the host; returns the losses. `minibatch_step` runs it as it is, or compiled
    (`compile_update`, `compile_step` around it); a minibatch split into shards on a CPU's threads, or the teams
    stacked on a GPU (`stacked_step`), are its other forms."""
    for parameter in team.parameters:  # what `optimizer.zero_grad()` does, which compiled graphs stop at
        parameter.grad = None
    losses = {**team.loss_module(minibatch), **team.algorithm.auxiliary_losses(minibatch)}
    total_loss(losses).backward()
    losses["grad_norm"] = apply_gradients(team)
    return losses


def learn_stacked(teams: Sequence[TrainingRun], step: Callable[[TensorDictBase], dict[str, torch.Tensor]],
                  batches: Sequence[TensorDictBase],
                  orders: Sequence[list[tuple[torch.Tensor, ...]]]) -> list[list[dict[str, torch.Tensor]]]:
    """The PPO epochs of K teams' updates as one: each minibatch of all teams (team k's kitchens in its own order),
    stacked along a team dim, goes through `step` (`stacked_step`). Returns each team's losses by minibatch, on the
    device, for `finish_update`."""
    stats = [[] for _ in teams]
    for kitchens_by_team in zip(*[[kitchens for order in team_orders for kitchens in order]
                                  for team_orders in orders]):
        minibatches = torch.stack([select_kitchens(batch, kitchens)
                                   for batch, kitchens in zip(batches, kitchens_by_team)])
        losses = step(minibatches)
        for index, team_stats in enumerate(stats):
            team_stats.append({key: value[index].detach().float() for key, value in losses.items()})
    return stats


def stacked_step(teams: Sequence[TrainingRun], loss: StackedLoss,
                 minibatches: TensorDictBase) -> dict[str, torch.Tensor]:
    """`ppo_step` of K teams at once on their minibatches [K, ...]: one loss (`StackedLoss`, the algorithm's
    `process_minibatch` included) and one backward to the teams' stacked parameters, each team's gradient zeroed
    where not finite and clipped to its own norm there (`clip_per_team`), then each team's Adam step; returns the
    losses, [K] each."""
    parameters = loss.parameters()
    losses = loss(minibatches, parameters)
    # The sum of the teams' losses: the gradient of each team's entry of a stacked parameter is its own loss's.
    gradients = torch.autograd.grad(total_loss(losses).sum(), list(parameters.values()), allow_unused=True)
    used = [index for index, gradient in enumerate(gradients) if gradient is not None]
    clipped, losses["grad_norm"] = clip_per_team([gradients[index] for index in used], teams[0].config.max_grad_norm)
    gradients = list(gradients)
    for index, gradient in zip(used, clipped):
        gradients[index] = gradient
    for index, team in enumerate(teams):
        for parameter, gradient in zip(team.parameters, gradients, strict=True):
            parameter.grad = None if gradient is None else gradient_for(parameter, [gradient[index]])
        team.optimizer.step()
        for parameter in team.parameters:
            parameter.grad = None
    return losses


def clip_per_team(gradients: list[torch.Tensor], max_norm: float) -> tuple[list[torch.Tensor], torch.Tensor]:
    """What `apply_gradients` does to one team's gradients before its Adam step, for K teams' gradients stacked
    along a leading team dim: non-finite entries zeroed, then each team's clipped to `max_norm` by their joint norm
    (as `clip_grad_norm_`). Returns the clipped gradients, new tensors (in-place writes into autograd's outputs keep
    Inductor from replaying the step as a CUDA graph), and the K norms before clipping."""
    gradients = [gradient.nan_to_num(0.0, 0.0, 0.0) for gradient in gradients]
    norms = torch.stack([gradient.flatten(1).norm(dim=1) for gradient in gradients]).norm(dim=0)
    scale = (max_norm / (norms + 1e-6)).clamp(max=1.0)
    return [gradient * scale.view(-1, *[1] * (gradient.dim() - 1)) for gradient in gradients], norms


class ShardPool(ThreadPoolExecutor):
    """The threads of a team's minibatch shards, whose `map` runs them at once or one after the other, whichever
    took less time over the last minibatches: the numbers are the same either way, but beside another busy
    process, a thread descheduled mid-minibatch holds up the step. Every `explore_every` maps it times the other
    way again, so it comes back when the machine is quiet."""

    def __init__(self, workers: int, explore_every: int = 32):
        super().__init__(workers, thread_name_prefix="shard")
        self.explore_every, self.maps = explore_every, 0
        self.seconds = {True: None, False: None}  # at once?: a moving average of a map's seconds

    def at_once(self) -> bool:
        """Whether the next map runs its shards at once: each way first, then the faster, the other now and then."""
        untimed = [way for way, seconds in self.seconds.items() if seconds is None]
        if untimed:
            return untimed[0]
        faster = self.seconds[True] <= self.seconds[False]
        return not faster if self.maps % self.explore_every == 0 else faster

    def map(self, fn, *iterables, **kwargs):
        self.maps += 1
        at_once = self.at_once()
        started = time.perf_counter()
        results = list(super().map(fn, *iterables, **kwargs) if at_once else map(fn, *iterables))
        seconds, average = time.perf_counter() - started, self.seconds[at_once]
        self.seconds[at_once] = seconds if average is None else 0.75 * average + 0.25 * seconds
        return iter(results)


def learning_pool(config: TrainConfig, num_teams: int) -> ThreadPoolExecutor | None:
    """The threads on which the teams learn at once (`parallel_teams`; 0: as many as the CPU cores allow with
    `threads` torch threads each), or on which a single team's minibatch shards run (`minibatch_shards`, a
    `ShardPool`); None for one after the other."""
    workers = config.runtime.parallel_teams or max(1, usable_cores() // config.runtime.threads)
    workers = min(workers, num_teams if num_teams > 1 else minibatch_shards(config))
    if workers < 2:
        return None
    return ThreadPoolExecutor(workers, thread_name_prefix="team") if num_teams > 1 else ShardPool(workers)


class UpdateRunner:
    """Runs the teams' updates of each batch (`learn`, the PPO epochs of one team, and `finish`, the end of its
    update) as the run options ask: all teams as one stacked computation (`stacked_update`), one after another,
    or on `parallel_teams` threads at once; a single team's minibatches split into `minibatch_shards` on threads,
    or compiled (`compile_update`). Every way gives each team the update it would have alone. A context manager:
    its threads live while it is entered."""

    def __init__(self, config: TrainConfig, teams: Sequence[TrainingRun], learn: Learn, finish: Finish):
        self.config, self.teams, self.learn, self.finish = config, list(teams), learn, finish
        self.stacked = stacked_update(teams) if learns_stacked(config, teams) else None
        if config.runtime.compile_update and self.stacked is None:
            for team in teams:
                team.compiled_step = compile_step(functools.partial(ppo_step, team), config.runtime.device)
        self.pool: ThreadPoolExecutor | None = None

    def __enter__(self) -> UpdateRunner:
        self.pool = learning_pool(self.config, len(self.teams))
        return self

    def __exit__(self, *exc) -> None:
        if self.pool is not None:
            self.pool.shutdown()
        self.pool = None

    def update(self, batches: Sequence[TensorDictBase], orders: Sequence[list]) -> list[tuple[dict[str, float], float]]:
        """Every team's update on its batch in its minibatch `orders`; returns each team's metrics and seconds. A
        team whose loss diverged is checkpointed with its last good weights once the teams before it are done, and
        its error raised.

        The modes that TorchRL's losses set while they run (recurrent mode, deterministic sampling) are
        process-wide; set here around all the teams, the losses' own settings and restorings, interleaved on
        threads, agree.
        """
        teams, pool = self.teams, self.pool

        def timed_learn(team, batch, team_orders, shard_pool=None):
            started = time.perf_counter()
            metrics = self.learn(team, batch, team_orders, functools.partial(minibatch_step, team, pool=shard_pool))
            return metrics, time.perf_counter() - started

        def timed_finish(team, batch, team_stats, restore_point, seconds):
            return self.finish(team, batch, team_stats, restore_point), seconds

        with set_recurrent_mode(True), set_exploration_type(teams[0].loss_module.deterministic_sampling_mode):
            arguments = list(zip(teams, batches, orders))
            if self.stacked is not None:
                started = time.perf_counter()
                restore_points = [RestorePoint(team) for team in teams]
                stats = learn_stacked(teams, self.stacked, batches, orders)
                seconds = time.perf_counter() - started  # the teams' one update
                pending = [functools.partial(timed_finish, *team_arguments, seconds)
                           for team_arguments in zip(teams, batches, stats, restore_points)]
            elif len(teams) == 1:
                pending = [functools.partial(timed_learn, *arguments[0], pool)]
            elif pool is None:  # each team learns when its result is asked for
                pending = [functools.partial(timed_learn, *team_arguments) for team_arguments in arguments]
            else:
                pending = [pool.submit(timed_learn, *team_arguments).result for team_arguments in arguments]
            results = []
            for team, result in zip(teams, pending):
                try:
                    results.append(result())
                except TrainingDiverged:
                    team.checkpoint()
                    raise
        return results
