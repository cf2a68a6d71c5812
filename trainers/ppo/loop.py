"""The PPO core on TorchRL: a `Collector` over `KitchenEnv`, GAE, `ClipPPOLoss`, loggers, checkpoints.

Read top to bottom: how an update starts (the learning rate, the training reward and its advantages, the minibatch
orders), its PPO epochs over minibatches of whole kitchen sequences, how it ends (the divergence check and the
metrics), when the teams checkpoint, then `train_teams()`: check the configs, ready the run directories and the
planner-guided starts, and `train_loop()`: build the env and the teams, resume or start fresh, and for every batch of
`num_envs x rollout_steps` steps per team update, log and checkpoint. The algorithm (`trainers.algorithms`: IPPO,
E3T, or one you register) changes the loop only through its named hooks; how the teams share the machine (threads,
shards, compilation, stacking on a GPU) is `trainers.ppo.runtime`'s; a run's start, logs, stop and resume are
`trainers.ppo.resume`'s; the command line is `trainers.train_command`'s.

    kitchen-train configs/ippo/mlp_ik.yaml seed=3 total_steps=1e6
    kitchen-train --resume runs/ippo_mlp_ik/seed3
"""

from __future__ import annotations

import math
import signal
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from tensordict import TensorDictBase
from torchrl.envs.utils import set_exploration_type
from torchrl.modules import set_recurrent_mode
from tqdm import tqdm

from torch_kitchen.env import team_rows
from torch_kitchen.keys import REWARD, SHAPED_REWARD, VALUE, VALUE_TARGET
from torch_kitchen.models import ActorCritic
from trainers.algorithms import check_algorithm
from trainers.checkpoint import LATEST
from trainers.config import ConfigError, TrainConfig, learning_keys
from trainers.ppo.advantages import compute_advantages, shaping_weight_at
from trainers.ppo.collection import make_collector
from trainers.ppo.distill import distill_planner_starts
from trainers.ppo.resume import (
    RunStopped,
    StopRequest,
    TrainingDiverged,
    already_trained,
    close_logs,
    open_logs,
    restore_streams,
    resume_or_start,
)
from trainers.ppo.runtime import Learner, UpdateRunner, team_policy, use_threads
from trainers.ppo.step import Losses, total_loss
from trainers.ppo.team import RestorePoint, TrainingTeam, build_teams, set_learning_rate

# ClipPPOLoss's outputs as logged (None: not logged); other entries (an algorithm's) go to losses/<name> for
# "loss_<name>" and to charts/<name> otherwise.
PPO_METRICS = {
    "loss_objective": "losses/policy",
    "loss_critic": "losses/value",
    "loss_entropy": "losses/entropy_loss",
    "entropy": "losses/entropy",
    "kl_approx": "losses/approx_kl",
    "clip_fraction": "losses/clip_fraction",
    "value_clip_fraction": "losses/value_clip_fraction",
    "ESS": "losses/effective_sample_size",
    "mean_ratio": "losses/mean_ratio",
    "max_ratio": "losses/max_ratio",
    "grad_norm": "losses/grad_norm",
}


def learning_rate_at(config: TrainConfig, update: int) -> float:
    """The learning rate of update `update` (1-based): annealed linearly towards 0 over the run if `anneal_lr`."""
    return config.ppo.lr * (1.0 - (update - 1) / config.num_updates) if config.ppo.anneal_lr else config.ppo.lr


def diverged(losses: dict[str, torch.Tensor], update: int, env_steps: int) -> TrainingDiverged:
    """The error naming every loss term of a minibatch that is NaN or infinite."""
    bad = [f"{metric_name(key)}={float(value.detach())}" for key, value in losses.items()
           if key.startswith("loss_") and not torch.isfinite(value)]
    return TrainingDiverged(
        f"{', '.join(bad)} at update {update} ({env_steps:,} env steps): training diverged; the weights before "
        "that update are in the latest checkpoint. Lower lr or max_grad_norm, or check the reward and model"
    )


def metric_name(key: str) -> str | None:
    """The logged name of a loss output (None: not logged)."""
    if key in PPO_METRICS:
        return PPO_METRICS[key]
    return f"losses/{key.removeprefix('loss_')}" if key.startswith("loss_") else f"charts/{key}"


def start_update(team: TrainingTeam, batch: TensorDictBase) -> tuple[list[tuple[torch.Tensor, ...]], dict[str, float]]:
    """The first part of an update of `team` on its batch [num_envs, rollout_steps], run in the team's random
    stream, one team after another: the counters, the learning rate, the training reward and GAE, the
    algorithm's batch hook, and the minibatch orders of every epoch (the update's only random draws). Returns
    the orders and the schedules the update runs with (its learning rate and shaping weight, as logged)."""
    config = team.config
    team.update += 1
    team.env_steps += batch.numel()
    schedules = {"charts/learning_rate": learning_rate_at(config, team.update),
                 "charts/shaping_weight": shaping_weight_at(config, team.env_steps)}
    set_learning_rate(config, team.optimizer, schedules["charts/learning_rate"])
    compute_advantages(batch, team.actor_critic.critic, config, schedules["charts/shaping_weight"])
    team.algorithm.process_batch(batch)
    # Drawn where the batch is: a GPU's minibatches then need nothing from the host.
    orders = [torch.randperm(config.num_envs, device=config.runtime.device).chunk(config.ppo.minibatches)
              for _ in range(config.ppo.epochs)]
    return orders, schedules


def update_teams(teams: Sequence[TrainingTeam], batches: Sequence[TensorDictBase], orders: Sequence[list],
                 runner: UpdateRunner) -> list[tuple[dict[str, float], float]]:
    """Every team's update on its batch, in its minibatch `orders` (`start_update`): the PPO epochs of the teams as
    the runtime has them learn (`learn`: each team on its own, on threads at once or not, or all as one stacked
    step on a GPU), then each team's end of update in turn (`finish_update`). Returns each team's metrics and the
    seconds its learning took. A team whose loss diverged is put back as it was before the update, checkpointed so
    once the teams before it are done, and its error raised.

    The modes that TorchRL's losses set while they run (recurrent mode, deterministic sampling) are process-wide;
    set here around all the teams, the losses' own settings and restorings, interleaved on threads, agree.
    """
    restore_points = [RestorePoint(team) for team in teams]

    def learn_teams(learner: Learner, indices: list[int]) -> tuple[list[list[Losses]], float]:
        return learn(learner, [batches[index] for index in indices], [orders[index] for index in indices])

    results = []
    with set_recurrent_mode(True), set_exploration_type(teams[0].loss_module.deterministic_sampling_mode):
        for learner, (stats, seconds) in zip(runner.learners, runner.map(learn_teams)):
            for index, team_stats in zip(learner.indices, stats):
                try:
                    metrics = finish_update(teams[index], batches[index], team_stats, restore_points[index])
                except TrainingDiverged:
                    teams[index].checkpoint()
                    raise
                results.append((metrics, seconds))
    return results


def learn(learner: Learner, batches: Sequence[TensorDictBase],
          orders: Sequence[list[tuple[torch.Tensor, ...]]]) -> tuple[list[list[Losses]], float]:
    """The PPO epochs of a learner's teams (a team, or several stacked) over minibatches of whole kitchen sequences,
    in their `orders`, each minibatch taken by the learner's step (`trainers.ppo.step.ppo_step`: the losses, their
    gradient, each team's clipped Adam step). Returns each team's losses by minibatch, on the device, and the
    seconds they took. Draws nothing at random and sets no global mode, so that several learners run at once on
    threads."""
    started = time.perf_counter()
    stats = [[] for _ in learner.teams]
    for minibatch in learner.minibatches(batches, orders):
        losses = learner.step(minibatch)
        for index, team_stats in enumerate(stats):
            team_stats.append({key: value[index].detach().float() for key, value in losses.items()})
    return stats, time.perf_counter() - started


def finish_update(team: TrainingTeam, batch: TensorDictBase, stats: list[dict[str, torch.Tensor]],
                  restore_point: RestorePoint) -> dict[str, float]:
    """The end of `team`'s update, after its minibatches' `stats` (losses on the device): raises TrainingDiverged if
    a loss was NaN or infinite, with the team put back to `restore_point`; else the algorithm's `after_update`, and
    the update's metrics, read from the device at once."""
    config = team.config
    finite = torch.stack([torch.isfinite(total_loss(minibatch_stats)) for minibatch_stats in stats])
    if not finite.all():  # the update's one read of the losses before its metrics
        restore_point.restore()
        raise diverged(stats[int(finite.logical_not().nonzero()[0])], team.update, team.env_steps)
    team.algorithm.after_update()

    on_device = {
        "charts/episode_return": batch.get(("next", *REWARD)).mean() * config.max_steps,
        "charts/shaped_return": batch.get(("next", *SHAPED_REWARD)).mean() * config.max_steps,
    }
    for key in stats[0]:
        if name := metric_name(key):
            on_device[name] = torch.stack([minibatch_stats[key] for minibatch_stats in stats]).mean()
    value, target = batch.get(VALUE), batch.get(VALUE_TARGET)
    target_variance = target.var()
    on_device["losses/explained_variance"] = 1 - (target - value).var() / target_variance
    ended = batch.get(("next", "done"))
    finished_sum, finished_count = (batch.get(("next", "episode_deliveries")) * ended).sum(), ended.sum().float()
    *read, target_variance, finished_sum, finished_count = torch.stack(
        [*on_device.values(), target_variance, finished_sum, finished_count]).tolist()
    metrics = dict(zip(on_device, read))
    if target_variance == 0:  # undefined where the targets do not vary
        del metrics["losses/explained_variance"]
    if finished_count:
        metrics["charts/episode_deliveries"] = finished_sum / finished_count
    return metrics


def log_update(teams: Sequence[TrainingTeam], learned: list[tuple[dict, float]], prepare_seconds: list[float],
               collect_seconds: float, steps_per_second: float,
               on_update: Callable[[int, dict], bool | None] | None) -> bool:
    """Logs each team's metrics of the update with its timings, and calls `on_update`; returns whether it asked to
    stop."""
    asked = False
    for team, (metrics, seconds), prepared in zip(teams, learned, prepare_seconds):
        metrics["charts/collect_seconds"] = collect_seconds
        metrics["charts/update_seconds"] = prepared + seconds
        metrics["charts/steps_per_second"] = steps_per_second
        for logger in team.loggers:
            logger.log_metrics(metrics, step=team.env_steps)
        asked |= bool(on_update(team.update, metrics)) if on_update is not None else False
    return asked


def snapshot_index(config: TrainConfig, update: int) -> int:
    """k where `update` is the k-th of the run's `snapshots` (at k/snapshots of its updates, rounded up); else 0."""
    points = [math.ceil(k * config.num_updates / config.snapshots) for k in range(1, config.snapshots + 1)]
    return points.index(update) + 1 if update in points else 0


def checkpoint_or_stop(teams: Sequence[TrainingTeam], asked: bool, signum: int | None, total_steps: int) -> bool:
    """After an update: every team checkpointed every `checkpoint_every` updates and at the last (the run's, or
    one `on_update` asked for); returns whether that was the last. RunStopped after a checkpoint where a signal
    came (`signum`)."""
    lead, update = teams[0].config, teams[0].update
    last = update == lead.num_updates or asked or signum is not None
    snapshot = snapshot_index(lead, update)
    if last or update % lead.checkpoint_every == 0 or snapshot:
        for team in teams:
            team.checkpoint(snapshot)
    if signum is not None:
        steps = sum(team.env_steps for team in teams)
        raise RunStopped(signum, f"stopped by {signal.Signals(signum).name} at update {update} "
                                 f"({steps:,} of {total_steps:,} env steps), checkpoint written")
    return last


def train(
    config: TrainConfig,
    actor_critic: ActorCritic | None = None,
    resume: bool = False,
    on_update: Callable[[int, dict], bool | None] | None = None,
    run: Path | None = None,
    allow_unsolvable: bool = False,
) -> Path:
    """Trains a team; returns the run directory (config.yaml, checkpoints/, tensorboard/, csv/).

    `actor_critic`: your own networks honouring the keys of `torch_kitchen.models` (default: built from
    `config.architecture`). `resume`: continue the run from its latest checkpoint. `on_update(update,
    metrics)`: called after every update; returning True stops the run after a checkpoint. `run`: the run
    directory (default `config.run_path`). `allow_unsolvable`: train on level files the checker calls
    unsolvable (with a warning) instead of refusing them. `runtime.teams > 1`: use `train_teams`.

    Raises ConfigError for a config no run can use (before any work), RunStopped after a signal (with a
    checkpoint), TrainingDiverged when a loss is NaN or infinite (with a checkpoint of the last good state).
    """
    if config.runtime.teams != 1:
        raise ConfigError(f"runtime.teams={config.runtime.teams}: train several teams with "
                          "train_teams(team_configs(config))")
    runs = None if run is None else [run]
    return train_teams([config], runs, resume, on_update, allow_unsolvable, actor_critic)[0]


def train_teams(
    configs: Sequence[TrainConfig],
    runs: Sequence[Path] | None = None,
    resume: bool = False,
    on_update: Callable[[int, dict], bool | None] | None = None,
    allow_unsolvable: bool = False,
    actor_critic: ActorCritic | None = None,
) -> list[Path]:
    """Trains one team per config (configs equal but for the seed, e.g. `team_configs(config)`) in one batch of
    kitchens; returns their run directories. Each team trains, logs and checkpoints exactly as a run of its own
    with its seed would (`train`), and can be resumed alone; `resume` continues them all from their checkpoints,
    which must be at the same update. `on_update(update, metrics)` is called for every team; `actor_critic` only
    for a single team. Raises as `train` does.
    """
    configs = check_teams(configs)
    runs = run_directories(configs, runs, resume, allow_unsolvable, actor_critic)
    use_threads(configs[0])
    if not resume:
        distill_planner_starts(configs, runs)
    return train_loop(configs, runs, resume, on_update, actor_critic)


def train_loop(configs: list[TrainConfig], runs: list[Path], resume: bool,
               on_update: Callable[[int, dict], bool | None] | None, actor_critic: ActorCritic | None) -> list[Path]:
    """PPO for the teams of `train_teams`, their configs checked and their run directories and starts ready: the
    kitchens and the teams built, each resumed or started fresh, then an update per collected batch, logged and
    checkpointed, until the budget, a signal or `on_update` stops them."""
    lead, num_teams = configs[0], len(configs)

    # ---------------------------------------------------------------- environment and teams
    teams, env = build_teams(configs, runs, actor_critic)
    policy = team_policy(lead, teams)
    runner = UpdateRunner(lead, teams)

    # ---------------------------------------------------------------- resume or start fresh
    saved = resume_or_start(teams, resume)  # the collector's first reset hands out restored kitchens
    policy.restack()  # the weights just loaded
    remaining = lead.num_updates - teams[0].update
    if already_trained(teams, remaining):
        return runs
    open_logs(teams, resume)
    frames_per_batch = num_teams * lead.frames_per_batch
    collector = make_collector(env, policy, frames_per_batch, remaining * frames_per_batch, lead.runtime.collector)
    restore_streams(teams, saved)  # after the collector, whose construction runs the policy once (and draws actions)
    progress = Progress(teams)

    # ---------------------------------------------------------------- training loop
    try:
        with StopRequest() as stop, runner:
            started = time.perf_counter()
            for batch in collector:
                collected = time.perf_counter()
                learned, prepare_seconds = learn_from_batch(teams, batch, runner)
                policy.restack()
                steps_per_second = batch.numel() / (time.perf_counter() - started)
                asked = log_update(teams, learned, prepare_seconds, collected - started, steps_per_second, on_update)
                progress.update(batch, steps_per_second)
                if checkpoint_or_stop(teams, asked, stop.signum, progress.total):
                    break
                started = time.perf_counter()
    finally:
        collector.shutdown()
        progress.close()
        close_logs(teams)
    return runs


def learn_from_batch(teams: list[TrainingTeam], batch: TensorDictBase, runner: UpdateRunner
                     ) -> tuple[list, list[float]]:
    """One update of every team on its rows of the collected `batch`: each team's advantages and minibatch order
    in its own stream (`start_update`), then their PPO epochs (`update_teams`). Returns what they learned and each
    team's seconds of preparation."""
    num_envs = teams[0].config.num_envs
    batches = [batch[team_rows(index, num_envs)] for index in range(len(teams))]
    orders, prepare_seconds, schedules = [], [], []
    for team, team_batch in zip(teams, batches):
        preparing = time.perf_counter()
        with team.stream.active():
            team_orders, team_schedules = start_update(team, team_batch)
        orders.append(team_orders)
        schedules.append(team_schedules)
        prepare_seconds.append(time.perf_counter() - preparing)
    learned = update_teams(teams, batches, orders, runner)
    for (metrics, _), schedule in zip(learned, schedules):
        metrics.update(schedule)  # the schedules the update ran with, logged beside what it learned
    return learned, prepare_seconds


def check_teams(configs: Sequence[TrainConfig]) -> list[TrainConfig]:
    """Teams trained in one batch share every setting but the seed; each is checked as a run of its own. Returns
    their configs with the algorithm's settings spelled out (`check_algorithm`)."""
    configs = [check_algorithm(config.check()) for config in configs]
    for config in configs:
        config.check_run_location()
        if config.runtime.teams != 1:
            raise ConfigError(f"runtime.teams={config.runtime.teams}: a team's own config has runtime.teams=1 "
                              "(see `team_configs`)")
    for config in configs[1:]:
        first = learning_keys(configs[0].to_dict())
        differ = [key for key, value in learning_keys(config.to_dict()).items()
                  if key != "seed" and value != first[key]]
        if differ:
            raise ConfigError(
                f"teams trained together share every setting but the seed; seed {config.seed} differs from seed "
                f"{configs[0].seed} in {', '.join(differ)}"
            )
    seeds = [config.seed for config in configs]
    if len(set(seeds)) < len(seeds):
        raise ConfigError(f"teams trained together need different seeds, got {seeds}")
    return configs


def run_directories(configs: Sequence[TrainConfig], runs: Sequence[Path] | None, resume: bool,
                    allow_unsolvable: bool, actor_critic: ActorCritic | None) -> list[Path]:
    """The teams' run directories (default: their configs' `run_path`), checked before any work; prints the
    levels' warnings and the config's note on its steps. ConfigError where a fresh run
    would overwrite a trained one, or a given actor_critic would train several teams."""
    lead = configs[0]
    for warning in lead.check_levels(allow_unsolvable):
        print(f"kitchen-train: warning: {warning}", file=sys.stderr)
    if note := lead.step_note():
        print(f"kitchen-train: {note}", file=sys.stderr)
    if actor_critic is not None and not isinstance(actor_critic, ActorCritic):
        raise ConfigError(f"actor_critic must be a torch_kitchen.models.ActorCritic(actor=..., critic=..., "
                          f"recurrent=...), got a {type(actor_critic).__name__}")
    if actor_critic is not None and len(configs) > 1:
        raise ConfigError("a given actor_critic trains one team; build the teams from config.architecture")
    runs = [Path(run) for run in runs] if runs is not None else [config.run_path for config in configs]
    for run in runs:
        if not resume and (run / "checkpoints" / LATEST).exists():
            raise ConfigError(
                f"{run} already holds a trained run; resume it with `kitchen-train --resume {run}`, or choose "
                "another name=, seed= or run_dir="
            )
    return runs


class Progress:
    """The run's progress bar (`progress`): env steps of all teams, with the mean deliveries of the episodes that
    ended in the last `RECENT_UPDATES` batches and the steps per second. A hidden bar reads nothing from the
    device; a shown one reads two numbers per batch."""

    RECENT_UPDATES = 10

    def __init__(self, teams: Sequence[TrainingTeam]):
        lead, num_teams = teams[0].config, len(teams)
        self.total = num_teams * lead.planned_steps
        self.bar = tqdm(total=self.total, initial=sum(team.env_steps for team in teams), unit="step",
                        unit_scale=True, disable=not lead.progress, dynamic_ncols=True)
        self.recent = deque(maxlen=self.RECENT_UPDATES)  # (deliveries summed, episodes) per batch

    def update(self, batch: TensorDictBase, steps_per_second: float) -> None:
        self.bar.update(batch.numel())
        if self.bar.disable:
            return
        done = batch["next", "done"].squeeze(-1)
        delivered = batch["next", "episode_deliveries"].squeeze(-1).where(done, 0).sum()
        self.recent.append(torch.stack([delivered.float(), done.sum().float()]).tolist())
        delivered, episodes = map(sum, zip(*self.recent))
        self.bar.set_postfix(deliveries=f"{delivered / max(1, episodes):.2f}", sps=f"{steps_per_second:,.0f}")

    def close(self) -> None:
        self.bar.close()
