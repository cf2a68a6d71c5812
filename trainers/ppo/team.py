"""A seed's team as it trains (`TrainingTeam`): its kitchens, networks, algorithm, TorchRL loss and optimizer,
built in the team's own random stream, its checkpoint, and the restore point an update that diverged goes back to;
and where its networks run and how its optimizer is set up for the run's options, below the runtime that steps them
(`trainers.ppo.runtime`, which decides how several teams share the machine), so imports run one way. The PPO loop
(`trainers.ppo.loop`) drives the runs; their step is `trainers.ppo.step`'s."""

from __future__ import annotations

import copy
import dataclasses
import shutil
from collections.abc import Sequence
from pathlib import Path

import torch
from tensordict.nn import TensorDictSequential
from torchrl.envs import EnvBase, Transform
from torchrl.objectives import ClipPPOLoss
from torchrl.record.loggers import Logger

from torch_kitchen.cpu_kernels import accelerate_cpu
from torch_kitchen.env import KitchenEnv, with_transforms
from torch_kitchen.keys import ACTION, ADVANTAGE, LOG_PROB, VALUE, VALUE_TARGET
from torch_kitchen.models import ActorCritic, make_actor_critic, model_identity
from torch_kitchen.partners.conventions import fingerprints
from torch_kitchen.teams import RandomStream, TeamTransform
from torch_kitchen.torchrl_internals import entropy_without_host_check, hold_value_clip_on_host
from trainers.algorithms import ALGORITHMS, Algorithm
from trainers.checkpoint import LATEST, capture_rng_states, save_checkpoint
from trainers.config import TrainConfig


def make_env(config: TrainConfig, num_envs: int | None = None, levels=None,
             seed: int | Sequence[int] | None = None) -> KitchenEnv:
    """The `KitchenEnv` of a config (evaluation passes its own batch, levels and seed; several teams their seeds)."""
    return KitchenEnv(
        num_envs=num_envs or config.num_envs,
        levels=config.levels if levels is None else levels,
        max_steps=config.max_steps,
        generator=config.generator,
        device=config.runtime.device,
        seed=config.seed if seed is None else seed,
    )


def with_model_transforms(env: KitchenEnv, actor_critic: ActorCritic, *extra: Transform):
    """`env` plus the transforms the model needs (episode-start flags and recurrent state for LSTMs, the partner
    context for E3T models), then `extra` ones (an algorithm's)."""
    return with_transforms(env, [*actor_critic.env_transforms(), *extra])


def place_networks(config: TrainConfig, actor_critic: ActorCritic, own_kernels: bool) -> None:
    """The team's networks on the run's device; on a CPU with `own_kernels` (networks built from the config, not a
    user's own) their layers swapped for this project's faster CPU kernels (`accelerate_cpu`)."""
    if own_kernels and torch.device(config.runtime.device).type == "cpu":
        accelerate_cpu(actor_critic.actor, actor_critic.critic)
    actor_critic.actor.to(config.runtime.device)
    actor_critic.critic.to(config.runtime.device)


def make_optimizer(config: TrainConfig, parameters: list[torch.nn.Parameter]) -> torch.optim.Adam:
    """The team's Adam: with `compile_update` its learning rate a tensor, so that annealing it changes a value
    rather than the compiled graph, and on a GPU its step counts on the device, as a CUDA graph needs; else fused,
    one kernel for all parameters instead of a few per tensor (3x faster on a CPU at hidden 256)."""
    if config.runtime.compile_update:
        lr = torch.tensor(config.ppo.lr, device=config.runtime.device)
        return torch.optim.Adam(parameters, lr=lr, eps=config.ppo.adam_eps, capturable=config.runtime.on_gpu)
    return torch.optim.Adam(parameters, lr=config.ppo.lr, eps=config.ppo.adam_eps, fused=True)


def set_learning_rate(config: TrainConfig, optimizer: torch.optim.Optimizer, lr: float) -> None:
    """The optimizer's learning rate for the next update: with `compile_update` written into the tensor the
    compiled step reads (made again after resuming a run saved without it)."""
    for group in optimizer.param_groups:
        if config.runtime.compile_update:
            if not isinstance(group["lr"], torch.Tensor):
                group["lr"] = torch.tensor(lr, device=config.runtime.device)
            group["lr"].fill_(lr)
        else:
            group["lr"] = lr


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
        clip_epsilon=config.ppo.clip_epsilon,
        entropy_coeff=config.ppo.entropy_coef,
        critic_coeff=config.ppo.value_coef,
        loss_critic_type="l2",
        normalize_advantage=False,
        clip_value=True,
        functional=False,  # PPO keeps no target networks: the modules run as they are
        log_explained_variance=False,  # the trainer logs it over the whole batch (`finish_update`), not a minibatch
    )
    loss.set_keys(action=ACTION, sample_log_prob=LOG_PROB, value=VALUE, advantage=ADVANTAGE, value_target=VALUE_TARGET)
    hold_value_clip_on_host(loss)
    entropy_without_host_check(loss)
    algorithm.configure_loss(loss)
    return loss


class TeamKitchens:
    """A team's rows of the shared `KitchenEnv`, checkpointed as `env.state_dict()` of a run of its own."""

    def __init__(self, env: KitchenEnv, team: int):
        self.env, self.team = env, team

    def state_dict(self) -> dict:
        return {"_extra_state": self.env.team_state(self.team)}

    def load_state_dict(self, state: dict) -> None:
        self.env.load_team_state(self.team, state["_extra_state"])


@dataclasses.dataclass
class TrainingTeam:
    """One seed's run as it trains: its config and run directory, the team's networks, algorithm, loss and
    optimizer, random stream, counters and loggers. A process trains one, or several in one batch of kitchens
    (`train_teams`); a finished run's team is loaded for play as a `trainers.evaluation.Team`."""

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
    # {fingerprint: name} of the scripted conventions it met: its algorithm's, and its init_from run's
    met: dict[str, str] = dataclasses.field(default_factory=dict)

    @property
    def checkpoint_path(self) -> Path:
        return self.run / "checkpoints" / LATEST

    def checkpoint(self, snapshot: int = 0) -> None:
        """Its checkpoint (`checkpoint_path`), and with `snapshot` k a copy kept as checkpoints/snapshot_<k>.pt
        (`snapshots`)."""
        with self.stream.active():
            rng = capture_rng_states()
        save_checkpoint(self.checkpoint_path, {
            "config": self.config.identity(),
            "model": self.identity,
            **{name: part.state_dict() for name, part in self.parts.items()},
            "algorithm": self.algorithm.state_dict(),
            "update": self.update,
            "env_steps": self.env_steps,
            "rng": rng,
            "met": dict(sorted(self.met.items())),
        })  # fmt: skip
        if snapshot:
            shutil.copyfile(self.checkpoint_path, self.checkpoint_path.with_name(f"snapshot_{snapshot}.pt"))


def team_configs(config: TrainConfig) -> list[TrainConfig]:
    """The configs of the `runtime.teams` teams of a config: seeds seed .. seed + teams - 1, each a run of its own."""
    alone = dataclasses.replace(config.runtime, teams=1)
    return [dataclasses.replace(config, seed=config.seed + team, runtime=alone) for team in range(config.runtime.teams)]


def build_team(config: TrainConfig, run: Path, kitchen: KitchenEnv, index: int,
               actor_critic: ActorCritic | None = None) -> TrainingTeam:
    """Team `index` of the batch: networks (from `config.architecture` unless given), algorithm, loss and
    optimizer, all built in the team's own random stream, seeded with its seed."""
    stream = RandomStream(config.seed, config.runtime.device)
    recipe = (config.architecture, kitchen.obs_shape, config.hidden, config.share_params)
    own_networks = actor_critic is None
    # Networks passed from Python are not rebuilt by name: their identity says so.
    identity = {**model_identity(*recipe), **({} if own_networks else {"given": True})}
    with stream.active():
        if own_networks:
            actor_critic = make_actor_critic(*recipe)
        place_networks(config, actor_critic, own_kernels=own_networks)
        algorithm = make_algorithm(config, actor_critic)
        loss_module = make_loss(config, actor_critic, algorithm)
        parameters = [*loss_module.parameters(), *algorithm.parameters()]
        optimizer = make_optimizer(config, parameters)
        parts = {"actor": actor_critic.actor, "critic": actor_critic.critic, "optimizer": optimizer,
                 "env": TeamKitchens(kitchen, index)}
        # The critic runs while acting: its values feed GAE.
        policy = actor_critic.acting_policy(*algorithm.acting_modules())
    return TrainingTeam(
        config=config, run=run, stream=stream, actor_critic=actor_critic, algorithm=algorithm, policy=policy,
        loss_module=loss_module, optimizer=optimizer, parameters=parameters, identity=identity, parts=parts,
        met=fingerprints(algorithm.met_conventions(config)),
    )  # fmt: skip


def build_teams(configs: Sequence[TrainConfig], runs: Sequence[Path], actor_critic: ActorCritic | None = None
                ) -> tuple[list[TrainingTeam], EnvBase]:
    """The teams of `configs` (`build_team`, one after another) in one batch of kitchens, and that batch with the
    transforms their model and algorithms need: each team's rows are `team_rows(index, num_envs)`."""
    lead = configs[0]
    kitchen = make_env(lead, num_envs=len(configs) * lead.num_envs, seed=[config.seed for config in configs])
    teams = [build_team(config, run, kitchen, index, actor_critic)
             for index, (config, run) in enumerate(zip(configs, runs))]
    return teams, with_model_transforms(kitchen, teams[0].actor_critic, *algorithm_transforms(teams))


def algorithm_transforms(teams: list[TrainingTeam]) -> list[Transform]:
    """The env transforms of the teams' algorithms: each team's own, on its rows, where there are several."""
    if len(teams) == 1:
        return teams[0].algorithm.env_transforms()
    per_team = [team.algorithm.env_transforms() for team in teams]
    return [TeamTransform(transforms, teams[0].config.num_envs) for transforms in zip(*per_team)]


class RestorePoint:
    """A team's weights and optimizer state as they were, copied on their device: an update whose loss diverged
    is undone from it, so that the update's minibatches need not stop to ask whether each loss was finite."""

    def __init__(self, team: TrainingTeam):
        self.team = team
        self.weights = [parameter.detach().clone() for parameter in team.parameters]
        self.optimizer = copy.deepcopy(team.optimizer.state_dict())

    def restore(self) -> None:
        with torch.no_grad():
            torch._foreach_copy_([parameter.data for parameter in self.team.parameters], self.weights)
        self.team.optimizer.load_state_dict(self.optimizer)
