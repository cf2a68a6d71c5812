"""Trained teams for evaluation: a run's team loaded from its checkpoint, a population of them by condition, and
the scripted cook as a team."""

from __future__ import annotations

import dataclasses
import glob
from dataclasses import dataclass, field
from pathlib import Path

import torch

from jax_env import layout_name
from torch_kitchen.cpu_kernels import accelerate_cpu
from torch_kitchen.models import ActorCritic, make_actor_critic
from torch_kitchen.partners.conventions import Convention, fingerprints
from torch_kitchen.partners.scripted_cook import SCRIPTED_COOK, scripted_actor_critic
from trainers.checkpoint import CheckpointError, load_checkpoint
from trainers.config import ConfigError, RuntimeConfig, TrainConfig
from trainers.config.compose import load_config

HUMAN_PROXY_RUN = "human_proxy_{grid}/seed0"  # a test grid's human proxy in the `human_proxies` folder
STRANGERS_CONDITION = "held-out strangers"  # the condition of a zoo's strangers (`trainers.zoo`)
LEARNED_CONDITION = "learned strangers"  # the condition of policies seated as strangers (`load_learned_strangers`)
SCRIPTED_CONDITION = "scripted cook"


@dataclass
class Team:
    """A trained team: its name ("<condition>/seed<k>"), training config, networks, kitchen size, and the env steps
    it was trained for (None where its file does not say, e.g. a team saved by hand)."""

    name: str
    condition: str
    config: TrainConfig
    actor_critic: ActorCritic
    obs_shape: tuple[int, int, int]
    checkpoint: str
    env_steps: int | None = None
    met: dict[str, str] = field(default_factory=dict)  # {fingerprint: name} of the conventions it trained with

    @property
    def fully_trained(self) -> bool:
        """Whether the team ran its config's whole budget (False for a run stopped early)."""
        return self.env_steps is None or self.env_steps >= self.config.planned_steps

    @property
    def regime(self) -> str:
        """"IK" (trained on the Infinite Kitchen) or "SK" (on fixed layouts)."""
        return "IK" if self.config.levels == "infinite" else "SK"

    @property
    def home(self) -> set[str] | None:
        """The names of the layouts a Single Kitchen team was trained on (None: an Infinite Kitchen team, at home
        anywhere); a layout file counts by its name, as the grids are named."""
        if self.regime == "IK":
            return None
        levels = self.config.levels
        return {layout_name(level) for level in ([levels] if isinstance(levels, str) else levels)}

    @property
    def is_outside_partner(self) -> bool:
        """Whether this team is a partner from outside every population: the scripted cook or a human proxy."""
        return self.condition == SCRIPTED_CONDITION or self.condition.startswith(HUMAN_PROXY_RUN.split("{")[0])

    @property
    def label(self) -> str:
        """The team's family in the paper's figures, e.g. "IPPO MLP IK", "E3T GNN SK"."""
        if self.config.architecture == SCRIPTED_COOK:
            return SCRIPTED_CONDITION
        algorithm = self.config.algorithm
        architecture = self.config.architecture.removeprefix(f"{algorithm}_")  # e3t_gnn -> GNN
        return f"{algorithm.upper()} {architecture.upper().replace('_', '+')} {self.regime}"


def load_team(checkpoint: str | Path, device: str = "cpu", condition: str = "",
              actor_critic: ActorCritic | None = None) -> Team:
    """The trained team of a checkpoint file or run directory (a CheckpointError says why one is unusable); its
    weights go into `actor_critic` where given (networks built in Python, as `train(actor_critic=...)` took them),
    else into the networks its header names."""
    state = load_checkpoint(checkpoint, map_location=device)
    where = state["path"]
    model = state["model"]
    if model.get("given") and actor_critic is None:
        raise CheckpointError(
            f"{where} was trained with networks built in Python (train(actor_critic=...)), which no name rebuilds: "
            "load it with load_team(RUN, actor_critic=your_networks), or register their builder "
            "(torch_kitchen.models.register_architecture) and train with architecture=<its name>"
        )
    try:
        config = load_config(base=state["config"], overrides=[f"runtime.device={device}"])
    except ConfigError as error:
        raise CheckpointError(f"{where} was saved with a config this version cannot read ({error})") from None
    own_networks = actor_critic is None
    try:
        if own_networks:
            actor_critic = make_actor_critic(model["architecture"], tuple(model["obs_shape"]), model["hidden"],
                                             model["share_params"], **model.get("options", {}))
    except ValueError as error:
        raise CheckpointError(
            f"{where} holds a {model['architecture']!r} model that cannot be built here ({error}); import the "
            "module that registers that architecture before loading it"
        ) from None
    if own_networks and torch.device(device).type == "cpu":
        accelerate_cpu(actor_critic.actor, actor_critic.critic)  # a user's networks stay as they were given
    try:
        actor_critic.actor.load_state_dict(state["actor"])
        actor_critic.critic.load_state_dict(state["critic"])
    except RuntimeError as error:
        raise CheckpointError(
            f"{where}: the weights do not fit the {model['architecture']!r} model its header describes "
            f"({str(error).splitlines()[0][:200]}); the file was written by another version or altered"
        ) from None
    actor_critic.actor.to(device).eval()
    actor_critic.critic.to(device).eval()
    condition = condition or config.name
    return Team(f"{condition}/seed{config.seed}", condition, config, actor_critic, tuple(model["obs_shape"]), where,
                state.get("env_steps"), dict(state.get("met", {})))


def scripted_cook_team(obs_shape: tuple[int, int, int], device: str = "cpu") -> Team:
    """The scripted cook as a team (both seats), for kitchens of `obs_shape`; at home on every grid."""
    return convention_team(Convention(), obs_shape, device, name="scripted cook", condition=SCRIPTED_CONDITION)


def convention_team(convention: Convention, obs_shape: tuple[int, int, int], device: str = "cpu", name: str = "",
                    condition: str = "") -> Team:
    """The scripted cook of `convention` as a team (both seats), named after the convention; at home anywhere."""
    config = TrainConfig(name=convention.name, architecture=SCRIPTED_COOK, runtime=RuntimeConfig(device=device))
    return Team(name or convention.name, condition or convention.name, config, scripted_actor_critic(convention),
                tuple(obs_shape), "(scripted)", met=fingerprints([convention]))


def load_learned_strangers(runs: dict[str, str | list[str]], device: str = "cpu") -> list[Team]:
    """The learned strangers: for each name, the teams of its runs (patterns as a condition's), each run's snapshots
    (`snapshots`: named "<name>/seed<k>@<j>of<n>") where it kept them, else its latest checkpoint."""
    strangers = []
    for name, teams in load_population(runs, device).items():
        for team in teams:
            snapshots = sorted(Path(team.checkpoint).parent.glob("snapshot_*.pt"),
                               key=lambda path: int(path.stem.split("_")[1]))
            if not snapshots:
                strangers.append(dataclasses.replace(team, condition=LEARNED_CONDITION))
            for j, path in enumerate(snapshots, start=1):
                snapshot = load_team(path, device, name)
                strangers.append(dataclasses.replace(snapshot, name=f"{team.name}@{j}of{len(snapshots)}",
                                                     condition=LEARNED_CONDITION))
    return strangers


def load_population(conditions: dict[str, str | list[str]], device: str = "cpu") -> dict[str, list[Team]]:
    """Condition name -> its teams, from run directories, checkpoint files or glob patterns of them."""
    matched = {condition: {pattern: sorted(glob.glob(pattern)) if glob.has_magic(pattern) else [pattern]
                           for pattern in ([patterns] if isinstance(patterns, str) else patterns)}
               for condition, patterns in conditions.items()}
    missing = [f"{condition} ({pattern})" for condition, found in matched.items()
               for pattern, paths in found.items() if not paths]
    if missing:  # every one at once: a newcomer learns in one try what to train or leave out
        raise CheckpointError(f"no run matches {len(missing)} of the conditions' patterns: {', '.join(missing)}; "
                              "train them first, or name your own runs with conditions={name: RUN_DIR_OR_GLOB}")
    population = {}
    for condition, found in matched.items():
        paths = [path for paths in found.values() for path in paths]
        teams = []
        for path in paths:
            try:
                teams.append(load_team(path, device, condition))
            except CheckpointError as error:
                raise CheckpointError(f"condition {condition!r}: {error}") from None
        names = [team.name for team in teams]
        for team in teams:  # two runs with one seed: tell them apart by position
            if names.count(team.name) > 1:
                team.name = f"{team.name}#{teams.index(team)}"
        population[condition] = teams
    return population
