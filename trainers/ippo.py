"""The PPO core on TorchRL: a `Collector` over `KitchenEnv`, GAE, `ClipPPOLoss`, loggers, checkpoints.

Read top to bottom: the helpers the loop uses, then `train()`: build the env, the networks and the algorithm,
the loss and the optimizer, resume or start fresh, then for every batch of `num_envs x rollout_steps` steps
compute the training reward, the advantages and a few epochs of PPO over minibatches of whole kitchen
sequences, log, and checkpoint. The algorithm (`trainers.algorithms`: IPPO, E3T, or one you register) changes
the loop only through its named hooks; this file knows none of them by name.

    kitchen-train configs/ippo/mlp_ik.yaml seed=3 total_steps=1e6
    kitchen-train --resume runs/ippo_mlp_ik/seed3
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import functools
import shutil
import signal
import sys
import time
from collections import deque
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import torch
from tensordict import TensorDictBase
from tensordict.nn import TensorDictModuleBase, TensorDictSequential
from torchrl.envs import Transform
from torchrl.envs.utils import set_exploration_type
from torchrl.modules import set_recurrent_mode
from torchrl.objectives import ClipPPOLoss
from torchrl.record.loggers import Logger, get_logger
from tqdm import tqdm

from torch_kitchen.cpu_kernels import accelerate_cpu
from torch_kitchen.env import KitchenEnv, with_transforms
from torch_kitchen.keys import ACTION, ADVANTAGE, LOG_PROB, VALUE, VALUE_TARGET
from torch_kitchen.models import ActorCritic, make_actor_critic
from torch_kitchen.teams import (
    RandomStream,
    StackedLoss,
    TeamPolicy,
    TeamTransform,
    stackable_acting,
    team_rows,
)
from torch_kitchen.torchrl_internals import (
    PurgingTensorboardLogger,
    entropy_without_host_check,
    hold_value_clip_on_host,
)
from trainers.advantages import generalized_advantages
from trainers.algorithms import ALGORITHMS, Algorithm
from trainers.checkpoint import (
    LATEST,
    CheckpointError,
    capture_rng_states,
    check_identity,
    load_checkpoint,
    model_identity,
    restore_rng_states,
    save_checkpoint,
)
from trainers.config import PLANNER_START, ConfigError, TrainConfig, config_help, load_config, save_config
from trainers.machine import usable_cores
from trainers.plugins import PluginError, add_plugin_option, import_plugins
from trainers.rollout import finished_episode_deliveries, make_collector

REWARD, SHAPED_REWARD = ("next", "agents", "reward"), ("next", "agents", "shaped_reward")
TRAIN_REWARD = ("next", "agents", "train_reward")  # sparse + shaping weight x shaped: the reward optimised

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
    "explained_variance": None,  # per minibatch; the trainer logs it over the whole batch instead
}


class RunStopped(Exception):
    """A run stopped by a signal (Ctrl-C: SIGINT, or SIGTERM); `exit_code` is 128 + the signal's number."""

    def __init__(self, signum: int, message: str):
        super().__init__(message)
        self.exit_code = 128 + signum


class TrainingDiverged(RuntimeError):
    """A loss became NaN or infinite; the last good state is in the run's latest checkpoint."""


# ------------------------------------------------------------------------------------------ building parts
def make_env(config: TrainConfig, num_envs: int | None = None, levels=None,
             seed: int | Sequence[int] | None = None) -> KitchenEnv:
    """The `KitchenEnv` of a config (evaluation passes its own batch, levels and seed; several teams their seeds)."""
    return KitchenEnv(
        num_envs=num_envs or config.num_envs,
        levels=config.levels if levels is None else levels,
        max_steps=config.max_steps,
        device=config.device,
        seed=config.seed if seed is None else seed,
    )


def with_model_transforms(env: KitchenEnv, actor_critic: ActorCritic, *extra: Transform):
    """`env` plus the transforms the model needs (episode-start flags and recurrent state for LSTMs, the partner
    context for E3T models), then `extra` ones (an algorithm's)."""
    return with_transforms(env, [*actor_critic.env_transforms(), *extra])


def make_algorithm(config: TrainConfig, actor_critic: ActorCritic) -> Algorithm:
    """The registered algorithm `config.algorithm`, checked against the model."""
    algorithm = ALGORITHMS[config.algorithm](config, actor_critic)
    algorithm.check()
    return algorithm


def make_loss(config: TrainConfig, actor_critic: ActorCritic, algorithm: Algorithm) -> ClipPPOLoss:
    """TorchRL's clipped PPO loss on the ("agents", ...) keys with the protocol's coefficients, as the algorithm
    configures it. The algorithm's `process_minibatch` standardises the advantages (by default pooled over the
    whole minibatch) before the minibatch is split into shards, so the loss leaves them as they are."""
    loss = ClipPPOLoss(
        algorithm.loss_actor(),
        actor_critic.critic,
        clip_epsilon=config.clip_epsilon,
        entropy_coeff=config.entropy_coef,
        critic_coeff=config.value_coef,
        loss_critic_type="l2",
        normalize_advantage=False,
        clip_value=True,
        functional=False,  # PPO keeps no target networks: the modules run as they are
    )
    loss.set_keys(action=ACTION, sample_log_prob=LOG_PROB, value=VALUE, advantage=ADVANTAGE, value_target=VALUE_TARGET)
    hold_value_clip_on_host(loss)
    entropy_without_host_check(loss)
    algorithm.configure_loss(loss)
    return loss


def make_loggers(config: TrainConfig, run: Path, purge_step: int | None) -> list[Logger]:
    """TorchRL loggers named by `config.loggers`, writing under `run/<name>`. TensorBoard drops the events a killed
    run wrote at steps >= `purge_step` (a resume); other backends (wandb, mlflow, ...) come from `get_logger`."""
    loggers = []
    for name in config.loggers:
        if name == "tensorboard":
            loggers.append(PurgingTensorboardLogger("tensorboard", str(run), purge_step=purge_step))
        else:  # the CSV files go to run/csv; a tracking service names the experiment after the run
            experiment = "csv" if name == "csv" else f"{config.name}-seed{config.seed}"
            loggers.append(get_logger(name, logger_name=str(run), experiment_name=experiment))
    return loggers


def hyperparameters(config: TrainConfig) -> dict[str, int | float | str | bool]:
    """The config as TensorBoard's hparams accept it (lists as text)."""
    return {key: value if isinstance(value, int | float | str | bool) else str(value)
            for key, value in config.to_dict().items()}


# ------------------------------------------------------------------------------------------- each update
def learning_rate_at(config: TrainConfig, update: int) -> float:
    """The learning rate of update `update` (1-based): annealed linearly towards 0 over the run if `anneal_lr`."""
    return config.lr * (1.0 - (update - 1) / config.num_updates) if config.anneal_lr else config.lr


def shaping_weight_at(config: TrainConfig, env_steps: int) -> float:
    if config.shaping_anneal_steps <= 0:
        return config.shaping_weight
    return config.shaping_weight * max(0.0, 1.0 - env_steps / config.shaping_anneal_steps)


def compute_advantages(batch: TensorDictBase, critic, config: TrainConfig, shaping_weight: float) -> None:
    """Writes the training reward (`TRAIN_REWARD`), GAE advantages and value targets into `batch` ([B, T],
    agents [B, T, 2]); the env's own rewards stay as they were.

    Values come from the collection pass (the policy runs the critic), so recurrent critics see the hidden
    state they had while acting; only the step after the batch needs a new critic call. The time limit ends
    an episode as a terminal state, as in the paper's JaxMARL code: no bootstrap across it.
    """
    reward = batch.get(REWARD) + shaping_weight * batch.get(SHAPED_REWARD)
    batch.set(TRAIN_REWARD, reward)
    done = batch.get(("next", "done")).unsqueeze(-2).expand_as(reward)  # [B, T, 1] -> [B, T, 2, 1]
    value = batch.get(VALUE)
    with torch.no_grad():
        after = critic(batch["next"][:, -1].clone()).get(VALUE)
    next_value = torch.cat([value[:, 1:], after.unsqueeze(1)], dim=1)
    advantage, target = generalized_advantages(
        config.gamma, config.gae_lambda, value, next_value, reward, done, done, time_dim=1
    )
    batch.set(ADVANTAGE, advantage)
    batch.set(VALUE_TARGET, target)


def total_loss(losses: dict[str, torch.Tensor]) -> torch.Tensor:
    """The sum of the "loss_*" terms (TorchRL's convention: each already weighted by its coefficient)."""
    return sum(value for key, value in losses.items() if key.startswith("loss_"))


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


# ------------------------------------------------------------------------------------- start, resume, stop
def start_fresh(run: Path) -> None:
    """A run directory without a checkpoint (a run killed before its first one) starts clean: its logs are
    removed, so the new run's logs are not appended to them."""
    for logs in ("csv", "tensorboard"):
        shutil.rmtree(run / logs, ignore_errors=True)


def restore(team: TrainingRun) -> dict:
    """Loads `team`'s latest checkpoint into its parts (networks, optimizer, its kitchens) and its algorithm, and
    sets its counters; returns the checkpoint (for its RNG states)."""
    state = load_checkpoint(team.checkpoint_path, map_location=team.config.device)
    check_identity(state, team.identity)
    for name, part in team.parts.items():
        part.load_state_dict(state[name])
    team.algorithm.load_state_dict(state["algorithm"])
    team.update, team.env_steps = state["update"], state["env_steps"]
    return state


def drop_csv_rows_after(csv_dir: Path, env_steps: int) -> None:
    """Removes the CSV rows a killed run logged after its last checkpoint, so a resumed run does not repeat them."""
    for path in csv_dir.rglob("*.csv"):
        rows = [line for line in path.read_text().splitlines() if line and int(float(line.split(",")[0])) <= env_steps]
        path.write_text("".join(row + "\n" for row in rows))


class StopRequest:
    """First Ctrl-C (or SIGTERM): finish the current update, checkpoint, stop. Second one: stop at once."""

    def __init__(self):
        self.signum: int | None = None
        self._previous = {}

    def __enter__(self):
        for signum in (signal.SIGINT, signal.SIGTERM):
            try:
                self._previous[signum] = signal.signal(signum, self._handle)
            except ValueError:  # not the main thread: leave signals alone
                pass
        return self

    def _handle(self, signum, frame):
        if self.signum is not None:
            raise RunStopped(signum, f"stopped by {signal.Signals(signum).name} before the update ended; "
                                     "its latest checkpoint is the last one written")
        self.signum = signum
        tqdm.write("stopping after this update (checkpoint first); press Ctrl-C again to stop at once")

    def __exit__(self, *exc):
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)


# ------------------------------------------------------------------------------------------------- teams
class TeamKitchens:
    """A team's rows of the shared `KitchenEnv`, checkpointed as `env.state_dict()` of a run of its own."""

    def __init__(self, env: KitchenEnv, team: int):
        self.env, self.team = env, team

    def state_dict(self) -> dict:
        return {"_extra_state": self.env.team_state(self.team)}

    def load_state_dict(self, state: dict) -> None:
        self.env.load_team_state(self.team, state["_extra_state"])


@dataclasses.dataclass
class TrainingRun:
    """One seed's run as it trains: its config and run directory, the team's networks, algorithm, loss and
    optimizer, random stream, counters and loggers. A process trains one, or several in one batch of kitchens
    (`train_teams`); a finished run's team is loaded for play as a `trainers.evaluate.Team`."""

    config: TrainConfig
    run: Path
    stream: RandomStream
    actor_critic: ActorCritic
    algorithm: Algorithm
    policy: TensorDictSequential  # acts while collecting: the actor, the algorithm's modules, the critic
    loss_module: ClipPPOLoss
    optimizer: torch.optim.Optimizer
    parameters: list[torch.nn.Parameter]
    identity: dict
    parts: dict  # what its checkpoint holds, by name: anything with state_dict() / load_state_dict()
    update: int = 0
    env_steps: int = 0
    loggers: list[Logger] = dataclasses.field(default_factory=list)
    compiled_step: Callable | None = None  # `ppo_step` compiled for this team (`compile_update`)

    @property
    def checkpoint_path(self) -> Path:
        return self.run / "checkpoints" / LATEST

    def checkpoint(self) -> None:
        with self.stream.active():
            rng = capture_rng_states()
        save_checkpoint(self.checkpoint_path, {
            "config": self.config.to_dict(),
            "model": self.identity,
            **{name: part.state_dict() for name, part in self.parts.items()},
            "algorithm": self.algorithm.state_dict(),
            "update": self.update,
            "env_steps": self.env_steps,
            "rng": rng,
        })  # fmt: skip


def team_configs(config: TrainConfig) -> list[TrainConfig]:
    """The configs of the `config.teams` teams of a config: seeds seed .. seed + teams - 1, each a run of its own."""
    return [dataclasses.replace(config, seed=config.seed + team, teams=1) for team in range(config.teams)]


def build_team(config: TrainConfig, run: Path, kitchen: KitchenEnv, index: int,
               actor_critic: ActorCritic | None = None) -> TrainingRun:
    """Team `index` of the batch: networks (from `config.architecture` unless given), algorithm, loss and
    optimizer, all built in the team's own random stream, seeded with its seed."""
    stream = RandomStream(config.seed, config.device)
    obs_shape = kitchen.kitchen.obs_shape
    with stream.active():
        if actor_critic is None:
            actor_critic = make_actor_critic(config.architecture, obs_shape, config.hidden, config.share_params)
            if torch.device(config.device).type == "cpu":
                accelerate_cpu(actor_critic.actor, actor_critic.critic)
        actor, critic = actor_critic.actor.to(config.device), actor_critic.critic.to(config.device)
        algorithm = make_algorithm(config, actor_critic)
        # The critic runs while acting: its values feed GAE.
        policy = actor_critic.acting_policy(*algorithm.acting_modules())
        loss_module = make_loss(config, actor_critic, algorithm)
        parameters = [*loss_module.parameters(), *algorithm.parameters()]
        if config.compile_update:
            # The learning rate a tensor, so that annealing it changes a value rather than the compiled graph; on a
            # GPU, Adam keeps its step counts on the device, as a CUDA graph needs.
            optimizer = torch.optim.Adam(parameters, lr=torch.tensor(config.lr, device=config.device),
                                         eps=config.adam_eps, capturable=torch.device(config.device).type == "cuda")
        else:
            # Fused: one kernel for all parameters instead of a few per tensor (3x faster on a CPU at hidden 256).
            optimizer = torch.optim.Adam(parameters, lr=config.lr, eps=config.adam_eps, fused=True)
    team = TrainingRun(
        config=config, run=run, stream=stream, actor_critic=actor_critic, algorithm=algorithm, policy=policy,
        loss_module=loss_module, optimizer=optimizer, parameters=parameters,
        identity=model_identity(config.architecture, obs_shape, config.hidden, config.share_params),
        parts={"actor": actor, "critic": critic, "optimizer": optimizer, "env": TeamKitchens(kitchen, index)},
    )  # fmt: skip
    if config.compile_update:
        team.compiled_step = compile_step(functools.partial(ppo_step, team), config.device)
    return team


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


def start_from(team: TrainingRun) -> None:
    """Loads into `team` the actor's and critic's weights that its `init_from` names (nothing to load from scratch):
    a run's latest checkpoint, or the scripted cook distilled first into the team's run folder. CheckpointError if
    that model is not the team's."""
    start = team.config.init_path(team.run)
    if start is None:
        return
    if team.config.init_from == PLANNER_START:
        from trainers.distill import distill_start  # distillation builds on this module

        distill_start(team.config, start)
    state = load_checkpoint(start, map_location=team.config.device)
    check_identity(state, team.identity)
    team.parts["actor"].load_state_dict(state["actor"])
    team.parts["critic"].load_state_dict(state["critic"])


def acts_stacked(config: TrainConfig, policies: Sequence[TensorDictModuleBase]) -> bool:
    """Whether the teams act as one stacked network (`TeamPolicy`'s `stack`): on a GPU, where the policies allow
    it, a team's kernel launches for all of them; on a CPU they act one after another, each with its sparse first
    layer."""
    return torch.device(config.device).type == "cuda" and stackable_acting(policies) is not None


def learns_stacked(config: TrainConfig, teams: Sequence[TrainingRun]) -> bool:
    """Whether the teams' minibatch steps run as one (`stacked_update`): on a GPU, where several teams learn and
    their model and algorithm allow it (feed-forward with shared parameters, `Algorithm.stackable`); on a CPU each
    team learns on its own, with its sparse first layer, on threads where `parallel_teams`."""
    stackable = (config.share_params and not teams[0].actor_critic.recurrent and teams[0].algorithm.stackable
                 and config.shards_per_minibatch == 1)
    return torch.device(config.device).type == "cuda" and len(teams) > 1 and stackable


def stacked_update(teams: Sequence[TrainingRun]) -> Callable[[TensorDictBase], dict[str, torch.Tensor]]:
    """The teams' minibatch step as one computation: `stacked_step` over their `StackedLoss`, compiled with
    `compile_update` (on a GPU, replayed as CUDA graphs)."""
    loss = StackedLoss([team.loss_module for team in teams], teams[0].algorithm.process_minibatch)
    step = functools.partial(stacked_step, teams, loss)
    return compile_step(step, teams[0].config.device) if teams[0].config.compile_update else step


def algorithm_transforms(teams: list[TrainingRun]) -> list[Transform]:
    """The env transforms of the teams' algorithms: each team's own, on its rows, where there are several."""
    if len(teams) == 1:
        return teams[0].algorithm.env_transforms()
    per_team = [team.algorithm.env_transforms() for team in teams]
    return [TeamTransform(transforms, teams[0].config.num_envs) for transforms in zip(*per_team)]


def start_update(team: TrainingRun, batch: TensorDictBase) -> list[tuple[torch.Tensor, ...]]:
    """The first part of an update of `team` on its batch [num_envs, rollout_steps], run in the team's random
    stream, one team after another: the counters, the learning rate, the training reward and GAE, the
    algorithm's batch hook, and the minibatch orders of every epoch (the update's only random draws)."""
    config = team.config
    team.update += 1
    team.env_steps += batch.numel()
    lr = learning_rate_at(config, team.update)
    for group in team.optimizer.param_groups:
        if config.compile_update:  # a tensor the compiled step reads, also after resuming a run saved without it
            if not isinstance(group["lr"], torch.Tensor):
                group["lr"] = torch.tensor(lr, device=config.device)
            group["lr"].fill_(lr)
        else:
            group["lr"] = lr
    compute_advantages(batch, team.actor_critic.critic, config, shaping_weight_at(config, team.env_steps))
    team.algorithm.process_batch(batch)
    # Drawn where the batch is: a GPU's minibatches then need nothing from the host.
    return [torch.randperm(config.num_envs, device=batch.device).chunk(config.minibatches)
            for _ in range(config.epochs)]


def select_kitchens(batch: TensorDictBase, kitchens: torch.Tensor) -> TensorDictBase:
    """batch[kitchens], the rows of those kitchens, gathered by `index_select`: indexing with a tensor gathers the
    uint8 observations element by element, 9x slower."""
    return batch.apply(lambda value: value.index_select(0, kitchens),
                       batch_size=torch.Size([len(kitchens), *batch.batch_size[1:]]))


def shard_gradients(team: TrainingRun, shard: TensorDictBase) -> tuple[dict[str, torch.Tensor], list]:
    """The losses of one shard of a minibatch and the gradient of their total for each of the team's parameters
    (None where a parameter does not take part)."""
    losses = {**team.loss_module(shard), **team.algorithm.auxiliary_losses(shard)}
    gradients = torch.autograd.grad(total_loss(losses), team.parameters, allow_unused=True)
    return losses, list(gradients)


def mean_over_shards(values: list[torch.Tensor]) -> torch.Tensor:
    return values[0] if len(values) == 1 else torch.stack(values).mean(0)


def gradient_for(parameter: torch.nn.Parameter, gradients: list[torch.Tensor | None]) -> torch.Tensor | None:
    """The mean of the shards' gradients of `parameter`, laid out in memory as the parameter is: fused Adam reads
    a parameter and its gradient element by element in memory order (backward() would lay it out so too)."""
    if gradients[0] is None:
        return None
    gradient = mean_over_shards(gradients)
    return gradient if gradient.stride() == parameter.stride() else torch.empty_like(parameter).copy_(gradient)


def minibatch_step(team: TrainingRun, minibatch: TensorDictBase,
                   pool: ThreadPoolExecutor | None) -> dict[str, torch.Tensor]:
    """One PPO step on a minibatch: the mean of its shards' losses and gradients (`minibatch_shards` equal parts
    by kitchen, on `pool`'s threads at once where given; one after the other gives the same numbers), clipped
    and applied; returns the losses. Reads nothing back from the device: whether the losses were finite is the
    caller's to check (`learn`, once per update)."""
    if team.compiled_step is not None:
        return team.compiled_step(minibatch)
    shards = minibatch.chunk(team.config.shards_per_minibatch, dim=0)
    run = pool.map if pool is not None and len(shards) > 1 else map
    shard_losses, gradients_by_shard = zip(*run(functools.partial(shard_gradients, team), shards))
    losses = {key: mean_over_shards([losses[key] for losses in shard_losses]) for key in shard_losses[0]}
    for parameter, gradients in zip(team.parameters, zip(*gradients_by_shard)):
        parameter.grad = gradient_for(parameter, list(gradients))
    losses["grad_norm"] = apply_gradients(team)
    return losses


def ppo_step(team: TrainingRun, minibatch: TensorDictBase) -> dict[str, torch.Tensor]:
    """`minibatch_step` as one function for `torch.compile` (`compile_update`; no shards): the loss, its backward,
    the clipping and the Adam step, with nothing read back on the host; returns the losses."""
    losses = {**team.loss_module(minibatch), **team.algorithm.auxiliary_losses(minibatch)}
    total_loss(losses).backward()
    losses["grad_norm"] = apply_gradients(team)
    for parameter in team.parameters:  # what `optimizer.zero_grad()` does, which compiled graphs stop at
        parameter.grad = None
    return losses


def apply_gradients(team: TrainingRun) -> torch.Tensor:
    """The Adam step on the gradients held by the team's parameters, clipped to `max_grad_norm`; returns their norm
    before clipping. A non-finite gradient is zeroed first: a diverged minibatch must leave the weights finite until
    the update's end undoes it (`learn`), since NaN weights would make the next minibatch's sampling fail (or assert
    on a GPU) before the check could say why."""
    for parameter in team.parameters:
        if parameter.grad is not None:
            parameter.grad.nan_to_num_(0.0, 0.0, 0.0)
    grad_norm = torch.nn.utils.clip_grad_norm_(team.parameters, team.config.max_grad_norm)
    team.optimizer.step()
    return grad_norm


class RestorePoint:
    """A team's weights and optimizer state as they were, copied on their device: an update whose loss diverged
    is undone from it, so that the update's minibatches need not stop to ask whether each loss was finite."""

    def __init__(self, team: TrainingRun):
        self.team = team
        self.weights = [parameter.detach().clone() for parameter in team.parameters]
        self.optimizer = copy.deepcopy(team.optimizer.state_dict())

    def restore(self) -> None:
        with torch.no_grad():
            torch._foreach_copy_([parameter.data for parameter in self.team.parameters], self.weights)
        self.team.optimizer.load_state_dict(self.optimizer)


def learn(team: TrainingRun, batch: TensorDictBase, orders: list[tuple[torch.Tensor, ...]],
          pool: ThreadPoolExecutor | None = None) -> dict[str, float]:
    """The PPO epochs of an update over minibatches of whole kitchen sequences, in `orders` (`start_update`),
    each minibatch's shards on `pool`'s threads where given; returns the update's metrics (`finish_update`). Draws
    nothing at random and sets no global mode, so that several teams learn at once on threads (`learn_teams`).
    Raises TrainingDiverged when a loss was NaN or infinite, with the weights and optimizer state put back as they
    were before the update."""
    restore_point = RestorePoint(team)
    stats = []
    for order in orders:
        for kitchens in order:
            minibatch = select_kitchens(batch, kitchens)
            team.algorithm.process_minibatch(minibatch)
            losses = minibatch_step(team, minibatch, pool)
            stats.append({key: value.detach().float() for key, value in losses.items()})
    return finish_update(team, batch, stats, restore_point)


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
    losses["grad_norm"] = clip_per_team([gradient for gradient in gradients if gradient is not None],
                                        teams[0].config.max_grad_norm)
    for index, team in enumerate(teams):
        for parameter, gradient in zip(team.parameters, gradients, strict=True):
            parameter.grad = None if gradient is None else gradient_for(parameter, [gradient[index]])
        team.optimizer.step()
        for parameter in team.parameters:
            parameter.grad = None
    return losses


def clip_per_team(gradients: list[torch.Tensor], max_norm: float) -> torch.Tensor:
    """What `apply_gradients` does to one team's gradients before its Adam step, for K teams' gradients stacked
    along a leading team dim, in place: non-finite entries zeroed, then each team's clipped to `max_norm` by their
    joint norm (as `clip_grad_norm_`). Returns the K norms before clipping."""
    for gradient in gradients:
        gradient.nan_to_num_(0.0, 0.0, 0.0)
    norms = torch.stack([gradient.flatten(1).norm(dim=1) for gradient in gradients]).norm(dim=0)
    scale = (max_norm / (norms + 1e-6)).clamp(max=1.0)
    for gradient in gradients:
        gradient.mul_(scale.view(-1, *[1] * (gradient.dim() - 1)))
    return norms


def finish_update(team: TrainingRun, batch: TensorDictBase, stats: list[dict[str, torch.Tensor]],
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
        "charts/episode_return": batch.get(REWARD).mean() * config.max_steps,
        "charts/shaped_return": batch.get(SHAPED_REWARD).mean() * config.max_steps,
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
    metrics["charts/learning_rate"] = learning_rate_at(config, team.update)
    metrics["charts/shaping_weight"] = shaping_weight_at(config, team.env_steps)
    return metrics


def learn_teams(teams: Sequence[TrainingRun], batches: Sequence[TensorDictBase], orders: Sequence[list],
                pool: ThreadPoolExecutor | None,
                stacked: Callable[[TensorDictBase], dict] | None = None) -> list[tuple[dict[str, float], float]]:
    """Every team's `learn` on its batch, on `pool`'s threads at once (None: one after the other; a single team
    runs its minibatches' shards there), or all teams' updates as one with `stacked` (`stacked_update`); returns
    each team's metrics and seconds. A team whose loss diverged is checkpointed with its last good weights once the
    teams before it are done, and its error raised.

    The modes that TorchRL's losses set while they run (recurrent mode, deterministic sampling) are process-wide;
    set here around all the teams, the losses' own settings and restorings, interleaved on threads, agree.
    """
    def timed_learn(team, batch, team_orders, shard_pool=None):
        started = time.perf_counter()
        metrics = learn(team, batch, team_orders, shard_pool)
        return metrics, time.perf_counter() - started

    def timed_finish(team, batch, team_stats, restore_point, seconds):
        return finish_update(team, batch, team_stats, restore_point), seconds

    with set_recurrent_mode(True), set_exploration_type(teams[0].loss_module.deterministic_sampling_mode):
        arguments = list(zip(teams, batches, orders))
        if stacked is not None:
            started = time.perf_counter()
            restore_points = [RestorePoint(team) for team in teams]
            stats = learn_stacked(teams, stacked, batches, orders)
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
    workers = config.parallel_teams or max(1, usable_cores() // config.threads)
    workers = min(workers, num_teams if num_teams > 1 else config.shards_per_minibatch)
    if workers < 2:
        return None
    return ThreadPoolExecutor(workers, thread_name_prefix="team") if num_teams > 1 else ShardPool(workers)


def check_teams(configs: Sequence[TrainConfig]) -> None:
    """Teams trained in one batch share every setting but the seed; each is checked as a run of its own."""
    for config in configs:
        config.check()
        config.check_run_location()
        if config.teams != 1:
            raise ConfigError(f"teams={config.teams}: a team's own config has teams=1 (see `team_configs`)")
    for config in configs[1:]:
        differ = [field.name for field in dataclasses.fields(TrainConfig)
                  if field.name != "seed" and getattr(config, field.name) != getattr(configs[0], field.name)]
        if differ:
            raise ConfigError(
                f"teams trained together share every setting but the seed; seed {config.seed} differs from seed "
                f"{configs[0].seed} in {', '.join(differ)}"
            )
    seeds = [config.seed for config in configs]
    if len(set(seeds)) < len(seeds):
        raise ConfigError(f"teams trained together need different seeds, got {seeds}")


# ------------------------------------------------------------------------------------------------ training
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
    unsolvable (with a warning) instead of refusing them. `config.teams > 1`: use `train_teams`.

    Raises ConfigError for a config no run can use (before any work), RunStopped after a signal (with a
    checkpoint), TrainingDiverged when a loss is NaN or infinite (with a checkpoint of the last good state).
    """
    if config.teams != 1:
        raise ConfigError(f"teams={config.teams}: train several teams with train_teams(team_configs(config))")
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
    check_teams(configs)
    lead, num_teams = configs[0], len(configs)
    for warning in lead.check_levels(allow_unsolvable):
        print(f"kitchen-train: warning: {warning}", file=sys.stderr)
    if note := lead.step_note():
        print(f"kitchen-train: {note}", file=sys.stderr)
    if actor_critic is not None and num_teams > 1:
        raise ConfigError("a given actor_critic trains one team; build the teams from config.architecture")
    torch.set_num_threads(lead.threads)
    runs = [Path(run) for run in runs] if runs is not None else [config.run_path for config in configs]
    for run in runs:
        if not resume and (run / "checkpoints" / LATEST).exists():
            raise ConfigError(
                f"{run} already holds a trained run; resume it with `kitchen-train --resume {run}`, or choose "
                "another name=, seed= or run_dir="
            )

    # ---------------------------------------------------------------- environment and teams
    kitchen = make_env(lead, num_envs=num_teams * lead.num_envs, seed=[config.seed for config in configs])
    teams = [build_team(config, run, kitchen, index, actor_critic)
             for index, (config, run) in enumerate(zip(configs, runs))]
    env = with_model_transforms(kitchen, teams[0].actor_critic, *algorithm_transforms(teams))
    policies = [team.policy for team in teams]
    if acts_stacked(lead, policies):  # compiled, the stacked networks replay as CUDA graphs
        compile_mode = "reduce-overhead" if lead.compile_policy else None
        policy = TeamPolicy(policies, [team.stream for team in teams], lead.num_envs, True, compile_mode)
    else:
        policies = [torch.compile(policy) if lead.compile_policy else policy for policy in policies]
        policy = TeamPolicy(policies, [team.stream for team in teams], lead.num_envs)

    stacked = stacked_update(teams) if learns_stacked(lead, teams) else None

    # ---------------------------------------------------------------- resume or start fresh
    saved = [None] * num_teams
    if resume:  # the collector's first reset hands out the restored kitchens
        saved = [restore(team) for team in teams]
        if len({team.update for team in teams}) > 1:
            at = ", ".join(f"{team.run} at update {team.update}" for team in teams)
            raise ConfigError(f"teams resumed together must be at the same update ({at}): resume them one by one")
        for team in teams:
            drop_csv_rows_after(team.run / "csv", team.env_steps)
    else:
        for team in teams:
            start_fresh(team.run)
            start_from(team)
    policy.restack()  # the weights just loaded
    for team in teams:
        team.run.mkdir(parents=True, exist_ok=True)
        save_config(team.config, team.run / "config.yaml")

    remaining = lead.num_updates - teams[0].update
    if remaining <= 0:
        for team in teams:
            print(f"{team.run}: already trained for {team.update} updates ({team.env_steps:,} steps); raise "
                  "total_steps to go on")
        return runs
    for team in teams:
        team.loggers = make_loggers(team.config, team.run, purge_step=team.env_steps + 1 if resume else None)
        if not resume:
            for logger in team.loggers:
                logger.log_hparams(hyperparameters(team.config))
    frames_per_batch = num_teams * lead.frames_per_batch
    collector = make_collector(env, policy, frames_per_batch, remaining * frames_per_batch)
    for team, state in zip(teams, saved):
        if state is not None:  # after the collector, whose construction runs the policy once (and draws actions)
            with team.stream.active():
                restore_rng_states(state["rng"])
    bar = tqdm(total=num_teams * lead.planned_steps, initial=sum(team.env_steps for team in teams), unit="step",
               unit_scale=True, disable=not lead.progress, dynamic_ncols=True)
    recent_deliveries = deque(maxlen=10 * num_teams * lead.num_envs)

    # ---------------------------------------------------------------- training loop
    try:
        with StopRequest() as stop, learning_pool(lead, num_teams) or contextlib.nullcontext() as pool:
            started = time.perf_counter()
            for batch in collector:
                collected = time.perf_counter()
                batches = [batch[team_rows(index, lead.num_envs)] for index in range(num_teams)]
                orders, prepare_seconds = [], []
                for team, team_batch in zip(teams, batches):
                    preparing = time.perf_counter()
                    with team.stream.active():
                        orders.append(start_update(team, team_batch))
                    prepare_seconds.append(time.perf_counter() - preparing)
                learned = learn_teams(teams, batches, orders, pool, stacked)
                policy.restack()
                now = time.perf_counter()
                asked = False
                for team, (metrics, seconds), prepared in zip(teams, learned, prepare_seconds):
                    metrics["charts/collect_seconds"] = collected - started
                    metrics["charts/update_seconds"] = prepared + seconds
                    metrics["charts/steps_per_second"] = batch.numel() / (now - started)
                    for logger in team.loggers:
                        logger.log_metrics(metrics, step=team.env_steps)
                    asked |= bool(on_update(team.update, metrics)) if on_update is not None else False
                recent_deliveries.extend(finished_episode_deliveries(batch).tolist())
                bar.update(batch.numel())
                recent = sum(recent_deliveries) / max(1, len(recent_deliveries))
                bar.set_postfix(deliveries=f"{recent:.2f}", sps=f"{metrics['charts/steps_per_second']:,.0f}")

                # --- checkpoint, and stop if asked
                update = teams[0].update
                last = update == lead.num_updates or asked or stop.signum is not None
                if last or update % lead.checkpoint_every == 0:
                    for team in teams:
                        team.checkpoint()
                if stop.signum is not None:
                    steps = sum(team.env_steps for team in teams)
                    raise RunStopped(stop.signum, f"stopped by {signal.Signals(stop.signum).name} at update {update} "
                                                  f"({steps:,} of {bar.total:,} env steps), checkpoint written")
                if last:
                    break
                started = time.perf_counter()
    finally:
        collector.shutdown()
        bar.close()
        for team in teams:
            for logger in team.loggers:
                logger.close()
    return runs


# -------------------------------------------------------------------------------------------- command line
def train_or_resume(configs: Sequence[TrainConfig]) -> list[Path]:
    """Trains the teams of `configs` together, or resumes them where every one has a checkpoint (teams already
    trained return at once), so running the same command again continues it. Teams of which only some have a
    checkpoint start over together: teams trained in one batch resume from one update."""
    checkpointed = [(config.run_path / "checkpoints" / LATEST).exists() for config in configs]
    if all(checkpointed):
        return train_teams(configs, resume=True)
    for config in configs:
        shutil.rmtree(config.run_path, ignore_errors=True)
    return train_teams(configs)


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="kitchen-train",
        description="Train a team with IPPO or E3T (TorchRL) on Single or Infinite Kitchen levels. Overrides: any "
                    "config key as key=value, e.g. seed=3 levels=cramped_room_7x7 total_steps=2e6.",
        epilog=config_help(TrainConfig),
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("config", nargs="?", help="a YAML config (configs/...); omit it with --resume")
    parser.add_argument("overrides", nargs="*", help="key=value config overrides")
    parser.add_argument("--resume", metavar="RUN_DIR", nargs="+",
                        help="continue the run in RUN_DIR from its latest checkpoint; several run directories (the "
                             "teams of a condition, e.g. runs/NAME/seed*) continue together in one batch; key=value "
                             "overrides may follow")
    parser.add_argument("--allow-unsolvable", action="store_true",
                        help="train on level files the solvability checker calls unsolvable (with a warning)")
    parser.add_argument("--eval-on-stop", action="store_true",
                        help="evaluate the team even when the run is stopped before total_steps")
    add_plugin_option(parser)
    return parser


def config_of(args: argparse.Namespace) -> tuple[list[TrainConfig], list[Path] | None]:
    """The teams a command line asks for: their configs (a YAML file and overrides, one per team, or saved runs'
    configs and overrides) and their run directories (None: the configs' own)."""
    if args.resume:
        # With --resume, key=value arguments are overrides (e.g. total_steps=...), the others run directories.
        arguments = [*args.resume, *([args.config] if args.config else []), *args.overrides]
        runs = [Path(item) for item in arguments if "=" not in item]
        overrides = [item for item in arguments if "=" in item]
        if any(item.startswith("teams=") for item in overrides):
            raise ConfigError("teams= starts new teams; resume several runs together by naming their directories")
        configs = []
        for run in runs:
            saved = run / "config.yaml"
            if not saved.is_file():
                raise ConfigError(f"{run} is not a run directory (no config.yaml in it)")
            configs.append(load_config(saved, overrides))
        return configs, runs
    if args.config is None:
        raise ConfigError("give a config file (e.g. configs/ippo/mlp_ik.yaml) or --resume RUN_DIR")
    if "=" in args.config:
        raise ConfigError(f"the first argument must be a config file, got the override {args.config!r}")
    return team_configs(load_config(args.config, args.overrides)), None


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    stopped = None
    try:
        import_plugins(args.plugins)
        configs, runs = config_of(args)
        runs = runs or [config.run_path for config in configs]
        try:
            train_teams(configs, runs, resume=bool(args.resume), allow_unsolvable=args.allow_unsolvable)
        except RunStopped as error:
            stopped = error
            print(f"kitchen-train: {error}; continue with `kitchen-train --resume {' '.join(map(str, runs))}`",
                  file=sys.stderr)
        if configs[0].eval_episodes > 0 and (stopped is None or args.eval_on_stop):
            from trainers.evaluate import report_trained_team

            for run in runs:
                report_trained_team(run)
    except (ConfigError, CheckpointError, ValueError, PluginError) as error:
        print(f"kitchen-train: error: {error}", file=sys.stderr)
        return 2
    except TrainingDiverged as error:
        print(f"kitchen-train: error: {error}", file=sys.stderr)
        return 1
    except RunStopped as error:  # a second signal, during the evaluation or while stopping
        print(f"kitchen-train: {error}", file=sys.stderr)
        return error.exit_code
    except KeyboardInterrupt:
        print("kitchen-train: stopped; resume from the last checkpoint with --resume", file=sys.stderr)
        return 130
    return stopped.exit_code if stopped is not None else 0


if __name__ == "__main__":
    sys.exit(main())
