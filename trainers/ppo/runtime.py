"""How the teams of one batch act and learn on this machine: the run options (`threads`, `parallel_teams`,
`minibatch_shards`, `compile_policy`, `compile_update`, the device), which change how fast a run goes and never what it
learns. Here are the run's speed choices (where a team's networks run and its optimizer: `trainers.ppo.team`), the
teams acting together (`team_policy`), and how the teams take their PPO steps (`UpdateRunner`, `Learner`): the step of
`trainers.ppo.step`, written once, with its gradients on a whole minibatch, on shards on threads, or for several teams
stacked (on a GPU), compiled or not.
"""

from __future__ import annotations

import functools
import time
from collections.abc import Callable, Iterator, Sequence
from concurrent.futures import ThreadPoolExecutor
from typing import TYPE_CHECKING, TypeVar

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase

from torch_kitchen.cpu_kernels import batch_observations
from torch_kitchen.keys import OBSERVATION
from torch_kitchen.teams import StackedLoss, TeamPolicy, stackable_acting
from trainers.algorithms import ALGORITHMS
from trainers.config import TrainConfig
from trainers.machine import usable_cores
from trainers.ppo.collection import learning_entries, select_kitchens
from trainers.ppo.step import (
    Gradients,
    GradientsOf,
    Losses,
    loss_gradients,
    mean_over_shards,
    ppo_step,
    team_gradients,
    total_loss,
)

if TYPE_CHECKING:
    from trainers.ppo.team import TrainingTeam

T = TypeVar("T")


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


def team_policy(config: TrainConfig, teams: Sequence[TrainingTeam]) -> TeamPolicy:
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
    """A minibatch step (`ppo_step` with its gradients' form) compiled (`compile_update`): the losses and their
    gradient one graph, the optimizer's step another. On a GPU in "reduce-overhead"
    mode, which replays the compiled graphs as CUDA graphs (a minibatch's launches at once); their outputs live in
    buffers that the next replay overwrites, and the update keeps every minibatch's losses, so these are copied
    out, all in one tensor."""
    compiled = torch.compile(step, mode="reduce-overhead" if torch.device(device).type == "cuda" else None,
                             dynamic=False)

    def run(minibatch: TensorDictBase) -> dict[str, torch.Tensor]:
        torch.compiler.cudagraph_mark_step_begin()
        # The loss and its gradient traced as one graph (`torch.autograd.grad` would otherwise break it in two);
        # torch's optimizer step breaks the graph around itself on purpose.
        with torch._dynamo.config.patch(trace_autograd_ops=True):
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


def learns_stacked(config: TrainConfig, teams: Sequence[TrainingTeam]) -> bool:
    """Whether the teams' minibatch steps run as one (`stacked_gradients`): on a GPU, where several teams learn and
    their model and algorithm allow it (feed-forward with shared parameters, `Algorithm.stackable`); on a CPU each
    team learns on its own, with its sparse first layer, on threads where `parallel_teams`."""
    stackable = (config.share_params and not teams[0].actor_critic.recurrent and teams[0].algorithm.stackable
                 and minibatch_shards(config) == 1)
    return config.runtime.on_gpu and len(teams) > 1 and stackable


def sharded_gradients(team: TrainingTeam, shards: int, pool: ThreadPoolExecutor | None) -> GradientsOf:
    """`team_gradients` as the mean of the minibatch's `shards` equal parts by kitchen (on `pool`'s threads at once
    where given; one after the other gives the same numbers), the minibatch made ready as a whole first."""

    def gradients_of(minibatch: TensorDictBase) -> tuple[Losses, Gradients]:
        team.algorithm.process_minibatch(minibatch)
        parts = minibatch.chunk(shards, dim=0)
        run = pool.map if pool is not None and len(parts) > 1 else map
        part_losses, part_gradients = zip(*run(functools.partial(loss_gradients, team), parts))
        losses = {key: mean_over_shards([losses[key] for losses in part_losses]).unsqueeze(0)
                  for key in part_losses[0]}
        gradients = [None if by_part[0] is None else mean_over_shards(list(by_part)).unsqueeze(0)
                     for by_part in zip(*part_gradients)]
        return losses, gradients

    return gradients_of


def stacked_gradients(teams: Sequence[TrainingTeam]) -> GradientsOf:
    """`team_gradients` of K teams on their minibatches stacked along a team dim, as one computation: their losses
    (`StackedLoss`, each team's own `process_minibatch` included) and one backward to their stacked parameters. The
    gradient of the sum of the teams' losses is, in each team's entry of a stacked parameter, its own loss's."""
    loss = StackedLoss([team.loss_module for team in teams], teams[0].algorithm.process_minibatch)

    def gradients_of(minibatches: TensorDictBase) -> tuple[Losses, Gradients]:
        parameters = loss.parameters()
        losses = loss(minibatches, parameters)
        gradients = torch.autograd.grad(total_loss(losses).sum(), list(parameters.values()), allow_unused=True)
        return {key: value.detach() for key, value in losses.items()}, list(gradients)

    return gradients_of


class Learner:
    """Teams that take each PPO step as one (`ppo_step`): a team alone, or on a GPU several teams stacked
    (`learns_stacked`). Their gradients come in the form the run options ask (a whole minibatch, shards on
    threads, or the teams stacked), and the step is compiled with `compile_update`."""

    def __init__(self, config: TrainConfig, teams: Sequence[TrainingTeam], pool: ThreadPoolExecutor | None = None,
                 indices: Sequence[int] | None = None):
        self.teams = list(teams)
        self.indices = list(range(len(self.teams)) if indices is None else indices)  # the teams' places in a batch
        shards = minibatch_shards(config)
        if len(self.teams) > 1:
            gradients_of = stacked_gradients(self.teams)
        elif shards > 1:
            gradients_of = sharded_gradients(self.teams[0], shards, pool)
        else:
            gradients_of = functools.partial(team_gradients, self.teams[0])
        step = functools.partial(ppo_step, self.teams, gradients_of)
        self.step = compile_step(step, config.runtime.device) if config.runtime.compile_update else step

    def minibatches(self, batches: Sequence[TensorDictBase],
                    orders: Sequence[list[tuple[torch.Tensor, ...]]]) -> Iterator[TensorDictBase]:
        """The minibatches of the teams' PPO epochs over their batches, in their `orders` (`start_update`): a
        team's kitchens, or the teams' stacked along a team dim, minibatch i of every team together. A team alone
        on a CPU hands each minibatch its sparse first layers' entries, found once per batch. A minibatch holds the
        batch's `learning_entries`."""
        batches = [learning_entries(batch) for batch in batches]
        found = None
        if len(self.teams) == 1:
            networks = [self.teams[0].actor_critic.actor, self.teams[0].actor_critic.critic]
            found = batch_observations(networks, batches[0].get(OBSERVATION))
        for kitchens_by_team in zip(*[[kitchens for order in team_orders for kitchens in order]
                                      for team_orders in orders]):
            minibatches = [select_kitchens(batch, kitchens) for batch, kitchens in zip(batches, kitchens_by_team)]
            if found is not None:
                found.hand_to(minibatches[0].get(OBSERVATION), kitchens_by_team[0])
            yield minibatches[0] if len(minibatches) == 1 else torch.stack(minibatches)


def with_torch_threads(threads: int) -> None:
    """A pool thread's start: torch's thread count (`runtime.threads`) set in it too. A new thread starts with
    OpenMP's default of one thread per core whatever `torch.set_num_threads` said in the main thread, and oneDNN's
    products, run on those threads, split a long sum between them on AVX2 processors: another order of summation
    than the same product on the main thread (docs/training.md, "Bit for bit")."""
    torch.set_num_threads(threads)


class TeamPool(ThreadPoolExecutor):
    """Threads on which the teams learn at once, each with `threads` torch threads (`with_torch_threads`)."""

    def __init__(self, workers: int, threads: int, thread_name_prefix: str = "team"):
        super().__init__(workers, thread_name_prefix=thread_name_prefix, initializer=with_torch_threads,
                         initargs=(threads,))


class ShardPool(TeamPool):
    """The threads of a team's minibatch shards, whose `map` runs them at once or one after the other, whichever
    took less time over the last minibatches: the numbers are the same either way, but beside another busy
    process, a thread descheduled mid-minibatch holds up the step. Every `explore_every` maps it times the other
    way again, so it comes back when the machine is quiet."""

    def __init__(self, workers: int, threads: int, explore_every: int = 32):
        super().__init__(workers, threads, thread_name_prefix="shard")
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
    threads = config.runtime.threads
    return TeamPool(workers, threads) if num_teams > 1 else ShardPool(workers, threads)


class UpdateRunner:
    """How the teams of a batch learn on this machine: as `Learner`s (all teams stacked as one on a GPU, where
    they allow it, else each team on its own), one after another, or on `parallel_teams` threads at once; a team
    alone has its minibatches' shards on threads (`minibatch_shards`). Every way gives each team the update it
    would have alone. A context manager: its threads live while it is entered."""

    def __init__(self, config: TrainConfig, teams: Sequence[TrainingTeam]):
        self.config, self.teams = config, list(teams)
        self.pool: ThreadPoolExecutor | None = None
        self.learners: list[Learner] = []

    def __enter__(self) -> UpdateRunner:
        self.pool = learning_pool(self.config, len(self.teams))
        if learns_stacked(self.config, self.teams):
            self.learners = [Learner(self.config, self.teams, indices=list(range(len(self.teams))))]
        else:
            shard_pool = self.pool if len(self.teams) == 1 else None
            self.learners = [Learner(self.config, [team], shard_pool, indices=[index])
                             for index, team in enumerate(self.teams)]
        return self

    def __exit__(self, *exc) -> None:
        if self.pool is not None:
            self.pool.shutdown()
        self.pool, self.learners = None, []

    def map(self, learn: Callable[[Learner, list[int]], T]) -> Iterator[T]:
        """`learn(learner, its teams' places)` of every learner, in order: on the teams' threads at once where
        there are several, else each when its result is asked for."""
        calls = [functools.partial(learn, learner, learner.indices) for learner in self.learners]
        if self.pool is None or len(calls) == 1:
            return (call() for call in calls)
        futures = [self.pool.submit(call) for call in calls]
        return (future.result() for future in futures)
