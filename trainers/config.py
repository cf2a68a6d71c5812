"""What a command's config is: one dataclass per command, every field with its one-line meaning, and the checks.

Two schemas: `TrainConfig` (a training run) and `EvalConfig` (an evaluation of trained teams). A training config
has two sections: `runtime` (`RuntimeConfig`: how the run uses the machine, not part of what the run is; an
evaluation's `runtime` is its device and threads, `DeviceConfig`) and `algorithm_config` (the algorithm's own
settings, which its class reads into a dataclass of its own with `settings_from`,
`trainers.algorithms.Algorithm.Settings`); their keys are `runtime.threads`, `algorithm_config.partner_epsilon`.
Values become a checked dataclass layer by layer (`merge_layer`, then `build_config`): OmegaConf merges and converts
them over structured configs built from the dataclasses (`structured_schema`), unknown keys and ill-typed values are
refused with the valid keys, and `check()` refuses values no run can use before any work starts, with one line (a
`ConfigError`) that says what to change. How the layers come from files and the command line: `trainers.composer`.
"""

from __future__ import annotations

import copy
import dataclasses
import difflib
import functools
import math
import random
import shutil
import types
import typing
from dataclasses import dataclass
from pathlib import Path

import jax
import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from jax_env import EXPANDED_LAYOUTS, classify_layout, load_layout
from jax_env.generator import NUM_HELDOUT_GENERATED, GeneratorConfig
from jax_env.generator import SIZES as GENERATOR_SIZES
from torch_kitchen.partners.conventions import STRANGER, TRAIN, ZOO_FILE, Convention, ConventionError, load_zoo


class ConfigError(ValueError):
    """A config file or override that cannot be used; the message says what to change."""


LOGGERS = ("tensorboard", "csv", "wandb", "mlflow", "trackio")  # TorchRL's `get_logger` backends
PLANNER_START = "scripted_cook"  # init_from: start from the scripted cook, distilled into the run's folder
TEACHER_MIXES = ("seed", "round")  # distill_teacher_mix: one teacher per seed, or one drawn per DAgger round
COLLECTORS = ("kitchen", "torchrl", "xla")  # runtime.collector: torch_kitchen.rollout's, TorchRL's, whole in XLA
EVAL_COLLECTORS = ("kitchen", "xla")  # EvalConfig.collector: torch at every step, or whole episodes in XLA
GENERATED_LEVELS = ("infinite", "heldout")  # `levels` values that name generated levels rather than layouts
# torch takes 64-bit seeds, but JAX (32-bit by default) keeps only a seed's low 32 bits: 2**32 + 5 would replay 5.
MAX_SEED = 2**32 - 1


def option(default, help: str, group: str | None = None):
    """A config field with its one-line meaning (`help`, listed by `config_help`); a list or dict default is copied
    for every instance. `group` starts a new group of keys in `config_help`."""
    metadata = {"help": help} if group is None else {"help": help, "group": group}
    if isinstance(default, list | dict) or dataclasses.is_dataclass(default):
        return dataclasses.field(default_factory=lambda: copy.deepcopy(default), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


@dataclass
class DeviceConfig:
    """Where a command runs: the `runtime` section of every command (an evaluation's whole section)."""

    device: str = option("cpu", '"cpu" or "cuda[:i]"; the env and the networks share it')
    threads: int = option(1, "torch CPU threads (1 is fastest for small networks on a shared CPU)")

    @property
    def on_gpu(self) -> bool:
        """Whether `device` is a CUDA device (where stacked teams, CUDA graphs and capturable Adam apply)."""
        return torch.device(self.device).type == "cuda"


@dataclass
class RuntimeConfig(DeviceConfig):
    """The run options of a training run: how it uses the machine, not what it learns. A fixed seed learns the same
    under any of them (up to float rounding where a key says so, and on another device), so they are not part of a
    run's identity: a checkpoint leaves them out (`TrainConfig.identity`), and a run resumes under others."""

    teams: int = option(
        1, "train seeds seed .. seed+teams-1 at once, one batch of teams x num_envs kitchens; each team writes "
           "its own run directory, as a run of its own would"
    )
    parallel_teams: int = option(
        0, "teams whose PPO updates run at once (or a team's minibatch shards), each on a thread of its own with "
           "`threads` torch threads (0: as many as the CPU cores allow); the results are those of one at a time"
    )
    minibatch_shards: int = option(
        0, "split every PPO minibatch into this many equal parts by kitchen and average their gradients, computed "
           "at once on threads when one team learns (IPPO; equal to the minibatch's gradient up to float rounding); "
           "0: 2 on a CPU at hidden >= 128 where the kitchens split evenly, else 1"
    )
    compile_policy: bool = option(
        False, "torch.compile the acting policy: the same actions, faster collection after a one-off compilation "
               "(on a GPU, the teams' stacked networks replay as CUDA graphs)"
    )
    collector: str = option(
        "xla", '"xla": MLP, ego_mlp and GNN teams and their LSTMs (shared or per-agent networks) act inside the '
               'kitchens\' XLA program, a whole batch one call (torch_kitchen.xla_rollout; actions drawn by JAX), '
               'E3T as "kitchen"; "kitchen": the '
               'kitchens\' own in-place rollout (torch_kitchen.rollout); "torchrl": TorchRL\'s Collector; the last '
               'two collect the same batches bit for bit, the first at a fraction of the host\'s work per step'
    )
    compile_update: bool = option(
        False, "torch.compile each PPO minibatch step (loss, backward, clipping, Adam with the learning rate a tensor) "
               "as one function; on a GPU its graphs replay as CUDA graphs, on a CPU the sparse first layers stay "
               "sparse inside them (at hidden 64 a quarter off an update, after a one-off compilation of 8-25 s); "
               "equal to eager up to float rounding"
    )


# What a resumed run may change besides its run options: where it is kept, how long it runs, what it writes.
RESUMABLE = ("name", "run_dir", "total_steps", "checkpoint_every", "snapshots", "loggers", "progress",
             "eval_episodes", "eval_heldout", "gif")


@dataclass
class TrainConfig:
    """Everything a self-play run (IPPO, E3T, anchored or kickstarted IPPO, or a registered algorithm) depends on.
    Defaults: the paper's Infinite Kitchen setting, an MLP."""

    # --- run
    name: str = option("ippo_mlp_ik", "the run directory is {run_dir}/{name}/seed{seed}", group="run")
    run_dir: str = option("runs", "the folder that holds the runs")
    seed: int = option(0, "seeds torch, the levels and the resets; the 6 teams of a condition are seeds 0..5")
    algorithm: str = option(
        "ippo", '"ippo" (self-play), "e3t" (mixed partner + partner model; e3t_* architectures), "anchored_ippo" '
                '(IPPO kept near its init_from policy by a KL penalty), "kickstarted_ippo" (IPPO with the scripted '
                'cook as a teacher throughout), "zoo_ippo" (a share of the kitchens seat a cook of the zoo beside the '
                'learner), or a registered one'
    )
    algorithm_config: dict[str, typing.Any] = option(
        {}, "the algorithm's own settings (algorithm_config.<key>, each algorithm's listed below; empty: its "
            "defaults, which a run's saved config spells out)"
    )

    # --- environment
    levels: str | list[str] = option(
        "infinite", '"infinite" (IK), a layout name or file (SK), or a list of them', group="environment"
    )
    kitchen_size: int = option(
        7, 'the side of the generated kitchens ("infinite", "heldout"): 7 (the paper\'s) or 9, each with its own '
           'held-out levels'
    )
    smaller_kitchens: float = option(
        0.0, "kitchen_size 9 only: the share of generated training kitchens drawn as a 7x7 kitchen inside the 9x9, "
             "counters around it, as the classic layouts' small rooms are (the held-out levels stay full size)"
    )
    intact_walls: float = option(
        GeneratorConfig.p_wall_intact, "the probability that a generated kitchen's continuous wall stays whole "
        "(the generator's p_wall_intact): more whole walls, more kitchens where items must pass over a counter"
    )
    max_steps: int = option(256, "episode length")
    num_envs: int = option(32, "kitchens stepped together")
    rollout_steps: int = option(256, "steps of every kitchen per update (one full episode by default)")
    total_steps: int = option(20_000_000, "env steps over the run (num_envs x rollout_steps per update)")

    # --- model
    architecture: str = option(
        "mlp", "mlp | mlp_lstm | gnn | gnn_lstm | ego_mlp (agent-centred, not in the paper), or a name given to "
        "register_architecture", group="model"
    )
    hidden: int = option(256, "hidden width: 256 for IK, 128 for SK in the paper")
    share_params: bool = option(True, "one network for both agents (IK) or one per agent (SK)")

    # --- PPO
    lr: float = option(2.5e-4, "Adam's learning rate", group="PPO")
    anneal_lr: bool = option(True, "anneal the learning rate linearly to 0 over the run")
    adam_eps: float = option(1e-5, "Adam's epsilon")
    epochs: int = option(4, "passes over each batch")
    minibatches: int = option(4, "split over kitchens, so every minibatch holds whole sequences (for recurrent models)")
    gamma: float = option(0.99, "discount factor")
    gae_lambda: float = option(0.95, "lambda of the generalised advantage estimate")
    clip_epsilon: float = option(0.2, "PPO clip range, for the policy ratio and the value")
    entropy_coef: float = option(0.01, "weight of the entropy bonus in the loss")
    value_coef: float = option(0.5, "weight of the value loss")
    max_grad_norm: float = option(0.5, "gradients are clipped to this global norm")
    shaping_weight: float = option(0.0, "weight of the shaped reward added to the sparse one (0: sparse only)")
    shaping_anneal_steps: int = option(0, "anneal shaping_weight linearly to 0 over this many env steps (0: constant)")

    # --- planner-guided start (kitchen-distill, then init_from)
    init_from: str = option(
        "", f'"{PLANNER_START}": distil the scripted cook first (kitchen-distill, into RUN/distilled) and start '
            "from it; or a run directory whose latest checkpoint's weights start this run, e.g. one kitchen-distill "
            "wrote ({seed} stands for the team's seed); empty: start from scratch",
        group="planner-guided start (kitchen-distill, then init_from)",
    )
    distill_rounds: int = option(7, "kitchen-distill: DAgger rounds of distill_kitchens x rollout_steps steps each")
    distill_kitchens: int = option(128, "kitchen-distill: kitchens rolled out at once in each round")
    distill_teacher_decay: float = option(
        0.5, "kitchen-distill: a seat takes the scripted cook's action with probability decay**round (round 0: always)"
    )
    distill_epochs: int = option(8, "kitchen-distill: passes over all the rounds' data after each round")
    distill_minibatch: int = option(4, "kitchen-distill: kitchens (whole sequences) per fitting step")
    distill_lr: float = option(3e-3, "kitchen-distill: Adam's rate, annealed linearly over the rounds")
    distill_move_order: str = option(
        "NSEW", "kitchen-distill: the scripted cook's choice among equally short moves, the first in this order (a "
                "permutation of NSEW; cooks with other orders keep other conventions)"
    )
    distill_symmetries: bool = option(
        True, "kitchen-distill: fit each minibatch under a random mirror image or quarter turn of its kitchens"
    )
    distill_teachers: list[str] = option(
        [], "kitchen-distill: conventions of the zoo's training split to learn from instead of the scripted cook "
            "(never a held-out stranger); empty: the scripted cook"
    )
    distill_teacher_mix: str = option(
        "seed", 'kitchen-distill, with distill_teachers: "seed" (seed k learns from teacher k mod n, one convention '
                'per seed) or "round" (each DAgger round from a teacher drawn by seed and round)'
    )
    zoo: str = option(
        ZOO_FILE, "the zoo file (kitchen-zoo) whose training conventions distill_teachers and algorithm zoo_ippo name"
    )
    learned_stranger: bool = option(
        False, "a learned stranger: distill_teachers name the zoo's held-out strangers, and the run is an evaluation "
               "partner (kitchen-eval's learned_strangers), never a team kitchen-eval evaluates"
    )

    # --- logging, checkpoints, final evaluation
    checkpoint_every: int = option(
        10,
        "updates between checkpoints (one is always written at the end)",
        group="logging, checkpoints, final evaluation",
    )
    snapshots: int = option(
        0, "keep a copy of the checkpoint at each k/snapshots of the run's updates (checkpoints/snapshot_<k>.pt; 3: "
           "FCP's partners at a third, two thirds and the end); 0: none"
    )
    loggers: list[str] = option(
        ["tensorboard", "csv"], f"TorchRL loggers, each under the run directory: {', '.join(LOGGERS)}"
    )
    progress: bool = option(True, "a progress bar with steps/s and recent deliveries")
    eval_episodes: int = option(8, "episodes per grid in the final self-play table (0: no evaluation)")
    eval_heldout: int = option(5, "held-out generated levels in that table, beside the 5 expanded classics")
    gif: bool = option(True, "a GIF of the trained team on the first evaluation grid")

    # --- run options
    runtime: RuntimeConfig = option(
        RuntimeConfig(), "how the run uses the machine, not what it learns: a run resumes under other run options, "
                         "and its checkpoints do not hold them", group="runtime"
    )

    @property
    def run_path(self) -> Path:
        return Path(self.run_dir) / self.name / f"seed{self.seed}"

    @property
    def frames_per_batch(self) -> int:
        return self.num_envs * self.rollout_steps

    @property
    def num_updates(self) -> int:
        """Updates of the run: total_steps rounded up to whole updates (`step_note` says so when it rounds)."""
        return max(1, -(-self.total_steps // self.frames_per_batch))

    @property
    def kitchens_per_minibatch(self) -> int:
        return self.num_envs // self.minibatches

    @property
    def planned_steps(self) -> int:
        """The env steps the run trains for: `num_updates` whole updates (at least total_steps)."""
        return self.num_updates * self.frames_per_batch

    def step_note(self) -> str | None:
        """One line for the trainer to print when total_steps is not a whole number of updates, else None."""
        if self.total_steps % self.frames_per_batch == 0:
            return None
        return (
            f"total_steps={self.total_steps:,} is not a multiple of the {self.frames_per_batch:,} steps of an update "
            f"(num_envs x rollout_steps): training {self.num_updates:,} updates = "
            f"{self.planned_steps:,} steps"
        )

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def identity(self) -> dict:
        """What the run is, without how it ran (`runtime`): what its checkpoints hold."""
        return {key: value for key, value in self.to_dict().items() if key != "runtime"}

    def changes_to_learning(self, trained: dict, resumable: tuple[str, ...] = RESUMABLE) -> dict[str, tuple]:
        """The keys where this config would change what a run with the identity `trained` (its checkpoint's config)
        learns, each as (trained value, this value). A resume may change only where the run is kept, how long it
        runs, its checkpoints, logs and final evaluation (`resumable`), and its run options. Keys the checkpoint
        predates are not compared."""
        asked = self.identity()
        return {key: (value, asked[key]) for key, value in trained.items()
                if key in asked and key not in resumable and value != asked[key]}

    @property
    def generator(self) -> GeneratorConfig:
        """The Infinite Kitchen generator's config that the environment keys name."""
        return GeneratorConfig(size=self.kitchen_size, p_smaller=self.smaller_kitchens, p_wall_intact=self.intact_walls)

    def distill_teacher(self, round_: int = 0) -> Convention:
        """The convention distillation learns from in DAgger round `round_` (and kickstarted IPPO all through): the
        scripted cook with `distill_move_order`, or of `distill_teachers` the seed's (mix "seed") or one drawn by
        seed and round (mix "round")."""
        if not self.distill_teachers:
            return Convention(move_order=self.distill_move_order)
        names = self.distill_teachers
        if self.distill_teacher_mix == "seed":
            name = names[self.seed % len(names)]
        else:
            name = names[random.Random(f"{self.seed}/{round_}").randrange(len(names))]
        return load_zoo(self.zoo, self.kitchen_size).convention(name, splits=self.teacher_splits)

    @property
    def teacher_splits(self) -> tuple[str, ...]:
        """The zoo's split `distill_teachers` name: its strangers for a learned stranger, else its training split."""
        return (STRANGER,) if self.learned_stranger else (TRAIN,)

    def check(self) -> TrainConfig:
        """Refuses values no run can use, before any work starts. Touches neither the file system nor the levels:
        the trainer also calls `check_run_location` and `check_levels`; nor the algorithm's own settings, which
        it checks (`trainers.algorithms.check_algorithm`: the registry is the algorithms' own)."""
        _check_types(self)
        _check_name(self.name)
        _check_seed(self.seed)
        counts = ["max_steps", "num_envs", "rollout_steps", "total_steps", "hidden", "epochs", "minibatches"]
        distilling = ["distill_rounds", "distill_kitchens", "distill_epochs", "distill_minibatch"]
        _at_least(self, [*counts, "checkpoint_every", *distilling], 1)
        weights = ["entropy_coef", "value_coef", "shaping_weight"]
        _at_least(self, ["eval_episodes", "snapshots", "shaping_anneal_steps", *weights], 0)
        if sorted(self.distill_move_order) != sorted("NSEW"):
            raise ConfigError(f"distill_move_order must be a permutation of NSEW, got {self.distill_move_order!r}")
        if self.distill_teacher_mix not in TEACHER_MIXES:
            raise ConfigError(f"distill_teacher_mix must be one of {', '.join(TEACHER_MIXES)}, got "
                              f"{self.distill_teacher_mix!r}")
        if self.learned_stranger and not self.distill_teachers:
            raise ConfigError("learned_stranger distils from held-out strangers: name them in distill_teachers")
        if self.distill_teachers:
            if self.distill_move_order != "NSEW":
                raise ConfigError("distill_move_order sets the scripted cook's moves; distill_teachers have their own "
                                  "conventions: give one or the other")
            try:
                zoo = load_zoo(self.zoo, self.kitchen_size)
                for name in self.distill_teachers:
                    zoo.convention(name, splits=self.teacher_splits)
            except ConventionError as error:
                raise ConfigError(f"distill_teachers: {error}") from None
        for name in ("lr", "adam_eps", "clip_epsilon", "max_grad_norm", "distill_lr"):
            if not getattr(self, name) > 0:
                raise ConfigError(f"{name} must be greater than 0, got {getattr(self, name)}")
        for name in ("gamma", "gae_lambda", "distill_teacher_decay"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"{name} must lie in [0, 1], got {getattr(self, name)}")
        if not 0 <= self.eval_heldout <= NUM_HELDOUT_GENERATED:
            raise ConfigError(
                f"eval_heldout must be between 0 and {NUM_HELDOUT_GENERATED} (the held-out levels), "
                f"got {self.eval_heldout}"
            )
        if not self.levels:
            raise ConfigError("levels is empty: give a layout name or file, a list of them, or 'infinite'")
        if self.kitchen_size not in GENERATOR_SIZES:
            raise ConfigError(f"kitchen_size must be one of {', '.join(map(str, GENERATOR_SIZES))} (the generated "
                              f"kitchens' side), got {self.kitchen_size}")
        if not 0.0 <= self.intact_walls <= 1.0:
            raise ConfigError(f"intact_walls is a probability in [0, 1], got {self.intact_walls}")
        if not 0.0 <= self.smaller_kitchens <= 1.0 or (self.smaller_kitchens and self.kitchen_size == 7):
            raise ConfigError(f"smaller_kitchens is a share in [0, 1] of 9x9 kitchens drawn 7x7 inside, got "
                              f"{self.smaller_kitchens} at kitchen_size {self.kitchen_size}")
        if isinstance(self.levels, list):
            for level in self.levels:
                if level in GENERATED_LEVELS:  # jax_env.Overcooked reads them only as the whole of `levels`
                    raise ConfigError(f"levels={level} stands alone: it cannot be one entry of a list {self.levels}")
        for logger in self.loggers:
            if logger not in LOGGERS:
                raise ConfigError(f"loggers holds {logger!r}; the TorchRL loggers are {', '.join(LOGGERS)}")
        if len(set(self.loggers)) < len(self.loggers):
            raise ConfigError(f"loggers names a logger twice: {self.loggers}")
        if self.num_envs % self.minibatches:
            raise ConfigError(
                f"minibatches ({self.minibatches}) must divide num_envs ({self.num_envs}): minibatches are whole "
                "kitchens' sequences"
            )
        self.check_runtime()
        return self

    def check_runtime(self) -> None:
        """Refuses run options no run can use (`runtime`), some of them with this run's shape."""
        runtime = self.runtime
        _at_least(runtime, ["threads", "teams"], 1, "runtime.")
        _at_least(runtime, ["parallel_teams", "minibatch_shards"], 0, "runtime.")
        if self.seed + runtime.teams - 1 > MAX_SEED:
            raise ConfigError(f"runtime.teams={runtime.teams} from seed={self.seed} go past the largest seed, "
                              f"{MAX_SEED}")
        if runtime.compile_update and runtime.minibatch_shards > 1:
            raise ConfigError(f"runtime.compile_update compiles a whole minibatch's step: runtime.minibatch_shards="
                              f"{runtime.minibatch_shards} splits it; set runtime.minibatch_shards=1 (or 0)")
        if runtime.minibatch_shards > 1 and self.kitchens_per_minibatch % runtime.minibatch_shards:
            raise ConfigError(
                f"runtime.minibatch_shards ({runtime.minibatch_shards}) must divide the {self.kitchens_per_minibatch} "
                "kitchens of a minibatch (num_envs / minibatches): shards are equal parts"
            )
        if runtime.collector not in COLLECTORS:
            raise ConfigError(f"runtime.collector={runtime.collector!r}: choose one of {', '.join(COLLECTORS)}")
        check_device(runtime.device, "runtime.device")
        for key in ("compile_update", "compile_policy"):
            if getattr(runtime, key) and not runtime.on_gpu:
                check_cpp_compiler(f"runtime.{key}")

    def check_run_location(self) -> None:
        """Refuses a run directory that cannot be made because a file stands where a folder must be. It looks at
        this machine's files, so `check()` leaves it to the trainer (evaluation reloads configs elsewhere)."""
        run_dir = Path(self.run_dir)
        for path in (self.run_path, *self.run_path.parents):
            if path.exists() and not path.is_dir():
                if path in (run_dir, *run_dir.parents):
                    raise ConfigError(f"run_dir={self.run_dir}: {path} is a file, not a folder")
                raise ConfigError(
                    f"name={self.name}: {path} is a file, not a folder (the run directory is {self.run_path})"
                )

    def init_path(self, run: Path) -> Path | None:
        """The run directory (or checkpoint file) whose weights start the run `run` of this seed; None: from
        scratch. The planner-guided start is distilled into the run's own folder."""
        if self.init_from == PLANNER_START:
            return run / "distilled"
        return Path(self.init_from.replace("{seed}", str(self.seed))) if self.init_from else None

    def check_levels(self, allow_unsolvable: bool = False) -> list[str]:
        """Loads every layout named in `levels` and refuses unsolvable ones (no team can deliver a soup there);
        with `allow_unsolvable`, returns one warning per unsolvable level instead, for the caller to print."""
        if isinstance(self.levels, str) and self.levels in GENERATED_LEVELS:
            return []  # the generator keeps only solvable levels
        layouts = {}
        for level in [self.levels] if isinstance(self.levels, str) else self.levels:
            try:
                layouts[level] = load_layout(level)
            except (ValueError, OSError) as error:
                raise ConfigError(f"levels: cannot load {level!r}: {error}") from None
        if len({layout.shape for layout in layouts.values()}) > 1:
            sizes = ", ".join(f"{level} is {layout.height}x{layout.width}" for level, layout in layouts.items())
            raise ConfigError(f"levels must all have one size, as they share one batch of kitchens: {sizes}")
        unsolvable = [level for level, layout in layouts.items() if classify_layout(layout) == "unsolvable"]
        if unsolvable and not allow_unsolvable:
            one = len(unsolvable) == 1
            which, it = (f"{unsolvable[0]} is", "it") if one else (f"{', '.join(unsolvable)} are", "them")
            raise ConfigError(
                f"levels: {which} unsolvable, no team can deliver a soup there (`kitchen-levels show FILE` says "
                f"why): fix the layout, or pass --allow-unsolvable to train on {it} anyway"
            )
        return [
            f"level {level} is unsolvable (no team can deliver a soup there); training on it anyway "
            "(--allow-unsolvable)"
            for level in unsolvable
        ]


@dataclass
class EvalConfig:
    """The self-play / cross-play evaluation of populations of trained teams (`kitchen-eval`).

    Every ordered pair of teams within a condition plays (i == j: self-play, i != j: cross-play), and so does
    every pair across the conditions named in `cross`; each pair plays `rollouts` episodes on every test grid.
    """

    # --- who plays
    conditions: dict[str, str | list[str]] = option(
        {}, "condition name -> its teams' run dirs or globs", group="who plays"
    )
    cross: list[list[str]] = option([], "[[cond_a, cond_b], ...] to cross-play")
    partner: bool = option(True, "every team also plays with the scripted cook, a partner outside every population")
    human_proxies: str = option(
        "", "a folder of human proxies (`kitchen-humans train`: human_proxy_<layout>/seed0): every team also plays "
        "with the proxy of each test grid that has one, both seats (e.g. runs; empty: none)"
    )

    strangers: str = option(
        "", "a zoo file (`kitchen-zoo`; the shipped one: configs/zoo/zoo.yaml): every team also plays beside each of "
        "its held-out strangers, both seats, on every test grid, scored against two of the stranger (empty: none)"
    )
    best_responses: dict[str, str] = option(
        {}, "held-out stranger -> the run of its best response (kitchen-train algorithm=zoo_ippo "
            "algorithm_config.best_response_to=NAME): the teams are also scored over it (BR-Prox)"
    )
    learned_strangers: dict[str, str | list[str]] = option(
        {}, "name -> runs or globs of learned strangers (policies no evaluated team met: learned_stranger runs, "
            "whose snapshots each join, or teams trained apart), seated beside every team as the strangers are"
    )

    # --- where and how long
    layouts: list[str] = option(
        list(EXPANDED_LAYOUTS), "test grids: layout names or text-grid files", group="where and how long"
    )
    heldout: int = option(NUM_HELDOUT_GENERATED, "the first N of the 100 held-out generated levels")
    kitchen_size: int = option(7, "the side of the held-out generated levels: 7, or 9 for teams trained at 9x9")
    rollouts: int = option(100, "episodes per pair and grid, actions sampled")
    max_steps: int = option(256, "episode length")

    # --- execution
    max_envs: int = option(
        8192, "kitchens stepped together (pairs x rollouts x grids are cut into batches of this)", group="execution"
    )
    workers: int = option(1, "processes that play the batches at once, each on a core of its own (the same numbers "
                          "with any)")
    collector: str = option(
        "xla", 'how the pairs play: "xla" (a batch whose teams are all feed-forward networks or scripted cooks plays '
        'inside one XLA program, actions drawn by JAX; the others as "kitchen") or "kitchen" (torch acts at every '
        "step)")
    seed: int = option(0, "the same seed gives the same numbers")
    progress: bool = option(True, "a progress bar")
    runtime: DeviceConfig = option(DeviceConfig(), "where it runs: the same numbers on any threads", group="runtime")

    # --- outputs
    out_dir: str = option("results/eval", "the folder of the tables, figures and GIFs", group="outputs")
    gifs: list[str] = option([], '"cond/seed0+cond/seed1@grid": agent 0, agent 1, grid')
    heatmaps: list[str] = option([], "grids on which to draw the cells agents visit")

    def check(self) -> EvalConfig:
        """Refuses values no evaluation can use, before any work starts."""
        _check_types(self)
        if self.kitchen_size not in GENERATOR_SIZES:
            raise ConfigError(f"kitchen_size must be one of {', '.join(map(str, GENERATOR_SIZES))}, got "
                              f"{self.kitchen_size}")
        _check_seed(self.seed)
        _at_least(self, ["rollouts", "max_steps", "max_envs", "workers"], 1)
        _at_least(self.runtime, ["threads"], 1, "runtime.")
        if self.collector not in EVAL_COLLECTORS:
            raise ConfigError(f"collector={self.collector!r}: choose one of {', '.join(EVAL_COLLECTORS)}")
        if not 0 <= self.heldout <= NUM_HELDOUT_GENERATED:
            raise ConfigError(
                f"heldout must be between 0 and {NUM_HELDOUT_GENERATED} (the held-out levels), got {self.heldout}"
            )
        if not self.layouts and not self.heldout:
            raise ConfigError("nothing to evaluate on: give layouts or heldout > 0")
        for pair in self.cross:
            if len(pair) != 2:
                raise ConfigError(f"cross holds pairs of condition names, got {pair!r}")
            for name in pair:
                if name not in self.conditions:
                    raise ConfigError(
                        f"cross names the condition {name!r}, which is not among the conditions: "
                        f"{', '.join(self.conditions) or '(none)'}"
                    )
        check_device(self.runtime.device, "runtime.device")
        return self


def check_cpp_compiler(key: str) -> None:
    """Refuses `key`=true where torch.compile would find no C++ compiler for its CPU kernels (Inductor's
    `cpp.cxx`), which it would only say at the first compiled call, deep inside a run."""
    import torch._inductor.config  # only where a run compiles (a second's import)

    names = [name for name in torch._inductor.config.cpp.cxx if name]
    if not any(shutil.which(name) for name in names):
        raise ConfigError(f"{key}=true compiles CPU kernels with a C++ compiler, and none of {', '.join(names)} is "
                          f"on the PATH: install one (e.g. g++, or name it in CXX) or set {key}=false")


def check_device(device: str, key: str = "device") -> None:
    """Refuses a device other than the CPU or a CUDA GPU that both torch and JAX see on this machine; `key` is the
    config key that names it."""
    allowed = f"use {key}=cpu, {key}=cuda or {key}=cuda:<index>"
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise ConfigError(f"{key}={device} is not a device: {allowed}") from None
    if parsed.type == "cpu" and not parsed.index:
        return
    if parsed.type != "cuda":
        raise ConfigError(f"{key}={device} is not supported: {allowed}")
    if not torch.cuda.is_available():
        raise ConfigError(f"{key}={device}, but torch sees no CUDA GPU on this machine: use {key}=cpu")
    index, count = parsed.index or 0, torch.cuda.device_count()
    if index >= count:
        raise ConfigError(f"{key}={device}, but torch sees {count} CUDA GPU(s) here: use cuda:0 to cuda:{count - 1}")
    try:  # the env runs in JAX on the same GPU (torch_kitchen.env.jax_device_for)
        jax_gpus = len(jax.devices("gpu"))
    except RuntimeError:
        jax_gpus = 0
    if index >= jax_gpus:
        raise ConfigError(
            f"{key}={device}, but JAX sees {jax_gpus} GPU(s) here (backend: {jax.default_backend()}): install a CUDA "
            f'build of JAX matching the driver (pip install -U "jax[cuda12]") or use {key}=cpu'
        )


def _check_types(config, prefix: str = "") -> None:
    """Refuses a field of the dataclass `config` whose value does not fit its type (a config built in Python skips
    `_merge`), its sections' fields too; a field is named with `prefix` (its section's, e.g. "runtime.")."""
    hints = type_hints(type(config))
    for field in dataclasses.fields(config):
        value, expected = getattr(config, field.name), hints[field.name]
        if dataclasses.is_dataclass(expected) and isinstance(value, expected):
            _check_types(value, f"{prefix}{field.name}.")
        elif not _matches(value, expected):
            raise ConfigError(f"{prefix}{field.name} must be {type_name(expected)}, got {value!r}")
        elif expected is float and not math.isfinite(value):  # YAML reads .inf and .nan, float() reads "nan"
            raise ConfigError(f"{prefix}{field.name} must be a finite number, got {value}")


def _at_least(config, names: list[str], low: int, prefix: str = "") -> None:
    """Refuses a field of `names` below `low`, named with `prefix` (its section's, e.g. "runtime.")."""
    for name in names:
        if not getattr(config, name) >= low:
            raise ConfigError(f"{prefix}{name} must be at least {low}, got {getattr(config, name)}")


def _check_seed(seed: int) -> None:
    if not 0 <= seed <= MAX_SEED:
        raise ConfigError(
            f"seed must be an integer in [0, {MAX_SEED}] (JAX keeps only the low 32 bits of a seed), got {seed}"
        )


def _check_name(name: str) -> None:
    """Refuses a run name that would put the run directory outside run_dir, or make it run_dir itself."""
    parts = Path(name).parts
    if not name.strip() or not parts or Path(name).is_absolute() or ".." in parts:
        raise ConfigError(
            f"name={name!r} must be a relative path inside run_dir, without '..' (e.g. name=ippo_mlp_ik or "
            "name=ablation/mlp)"
        )


def _fields(schema: type) -> list[str]:
    return [f.name for f in dataclasses.fields(schema)]


def _matches(value, expected) -> bool:
    """Whether a YAML value fits a field type built from str, int, float, bool, list, dict and `|`."""
    origin, args = typing.get_origin(expected), typing.get_args(expected)
    if expected is typing.Any:
        return True
    if origin in (typing.Union, types.UnionType):
        return any(_matches(value, arg) for arg in args)
    if origin is list:
        return isinstance(value, list) and all(_matches(item, args[0]) for item in value)
    if origin is dict:
        return isinstance(value, dict) and all(
            _matches(key, args[0]) and _matches(item, args[1]) for key, item in value.items()
        )
    if isinstance(value, bool):
        return expected is bool
    if expected is float:
        return isinstance(value, int | float)
    return isinstance(value, expected)


def type_name(expected) -> str:
    if expected is typing.Any:
        return "any value"
    if typing.get_origin(expected) is None:
        return expected.__name__
    return str(expected).replace("typing.", "")


@functools.cache
def type_hints(schema: type) -> dict:
    """`typing.get_type_hints(schema)`, read once per schema (a config load asks for it hundreds of times); the
    caller must not change the mapping."""
    return typing.get_type_hints(schema)


@functools.cache
def config_keys(schema: type) -> tuple[str, ...]:
    """The keys of `schema`, a section's as `section.key` (`runtime.device`)."""
    hints = type_hints(schema)
    return tuple(key for field in dataclasses.fields(schema)
                 for key in ([f"{field.name}.{inner}" for inner in config_keys(hints[field.name])]
                             if dataclasses.is_dataclass(hints[field.name]) else [field.name]))


def is_config_key(schema: type, key: str) -> bool:
    """Whether `key` names a key of `schema`: one of `config_keys`, or any `algorithm_config.<key>` (the
    algorithm checks its own)."""
    return key in config_keys(schema) or (key.startswith("algorithm_config.") and "algorithm_config" in
                                          type_hints(schema))


def unknown_key(schema: type, key: str, source: str) -> ConfigError:
    keys = config_keys(schema)
    moved = [known for known in keys if known.endswith(f".{key}")]
    hint = moved or difflib.get_close_matches(key, keys, n=1)
    did_you_mean = f" (did you mean {hint[0]!r}?)" if hint else ""
    return ConfigError(f"unknown config key {key!r} in {source}{did_you_mean}; valid keys: {', '.join(keys)}")


# ------------------------------------------------------------------------------- merging, on OmegaConf
def _is_union(expected) -> bool:
    return typing.get_origin(expected) in (typing.Union, types.UnionType)


def _omegaconf_type(expected):
    """A field type as OmegaConf can hold it: it types no unions (`levels: str | list[str]`), so those are Any
    there and `_merge` checks them; a section is its own structured config."""
    origin, args = typing.get_origin(expected), typing.get_args(expected)
    if _is_union(expected):
        return typing.Any
    if dataclasses.is_dataclass(expected):
        return structured_schema(expected)
    if origin is list:
        return list[_omegaconf_type(args[0])]
    if origin is dict:
        return dict[args[0], _omegaconf_type(args[1])]
    return expected


@functools.cache
def structured_schema(schema: type) -> type:
    """`schema` as a dataclass OmegaConf can type: the same fields and defaults, unions as Any."""
    hints = typing.get_type_hints(schema)
    fields = [(field.name, _omegaconf_type(hints[field.name]),
               dataclasses.field(default_factory=structured_schema(hints[field.name]))  # a section: its own defaults
               if dataclasses.is_dataclass(hints[field.name]) else
               dataclasses.field(default=field.default, default_factory=field.default_factory))
              for field in dataclasses.fields(schema)]  # fmt: skip
    return dataclasses.make_dataclass(schema.__name__, fields)


def _merges_by_key(expected) -> bool:
    """Whether a later layer's mapping for a field of this type merges into the earlier one key by key (a section:
    `runtime`, `algorithm_config`), rather than replacing it as any other value (e.g. EvalConfig's `conditions`)."""
    return dataclasses.is_dataclass(expected) or expected == dict[str, typing.Any]


def _checked_layer(schema: type, values: dict, source: str, prefix: str = "", root: type | None = None) -> dict:
    """`values` from `source` with every key known to `schema` (a section's keys named `prefix`key) and every value
    of a type OmegaConf would not catch refused with one line, and what YAML reads otherwise made readable."""
    hints, layer = type_hints(schema), {}
    for key, value in values.items():
        if key not in hints:
            raise unknown_key(root or schema, f"{prefix}{key}", source)
        expected = hints[key]
        if dataclasses.is_dataclass(expected):
            if not isinstance(value, dict):
                raise ConfigError(f"{prefix}{key} in {source} must be a mapping of its keys "
                                  f"({', '.join(_fields(expected))}), got {value!r}")
            layer[key] = _checked_layer(expected, value, source, f"{prefix}{key}.", root or schema)
            continue
        if expected is str and value is None:  # `key=` on the command line: the empty string
            value = ""
        if expected is int and isinstance(value, str | float) and not isinstance(value, bool):
            try:  # 2e6 is a float to YAML and a string to PyYAML; OmegaConf takes neither as an int
                value = int(float(value)) if float(value).is_integer() else value
            except ValueError:
                pass
        # OmegaConf reads 3 as True, and a scalar for a mapping as an error of its own wording
        strict = (_is_union(expected) or expected is bool or isinstance(value, bool)
                  or typing.get_origin(expected) is dict)
        if strict and not _matches(value, expected):
            raise ConfigError(f"{prefix}{key} in {source} must be {type_name(expected)}, got {value!r}")
        layer[key] = value
    return layer


def merge_layer(schema: type, merged: DictConfig, values: dict, source: str, prefix: str = "") -> DictConfig:
    """`values` (from `source`: a file, the command line, a saved run) merged over `merged` by OmegaConf, which
    converts what it can (e.g. "1e-3" to a float); a ConfigError names the key (after `prefix`, that of the section
    `schema` is), its type and the source."""
    hints, layer = type_hints(schema), _checked_layer(schema, values, source, prefix)
    try:
        # A later layer replaces a mapping, as it replaces any value, instead of merging (OmegaConf.merge copies
        # `merged`: only a mapping cleared first needs a copy of its own).
        replaced = [key for key, value in layer.items() if isinstance(value, dict) and not _merges_by_key(hints[key])]
        if replaced:
            merged = merged.copy()
            for key in replaced:
                merged[key] = {}
        return OmegaConf.merge(merged, layer)
    except OmegaConfBaseException as error:
        key = str(getattr(error, "full_key", "") or "") or next(iter(layer))
        expected, value = _at_path(hints, layer, key)
        raise ConfigError(f"{prefix}{key} in {source} must be {type_name(expected)}, got {value!r}") from None


def _at_path(hints: dict, layer: dict, key: str) -> tuple[type, object]:
    """The type and the layer's value of the (dotted) `key`."""
    head, _, rest = key.partition(".")
    expected, value = hints.get(head, object), layer.get(head)
    if rest and dataclasses.is_dataclass(expected) and isinstance(value, dict):
        return _at_path(type_hints(expected), value, rest)
    return expected, value


def build_config(schema: type, values: dict):
    """The dataclass `schema` from merged plain values, its sections built as their own dataclasses."""
    hints = type_hints(schema)
    return schema(**{key: build_config(hints[key], value) if dataclasses.is_dataclass(hints[key]) else value
                     for key, value in values.items()})


def settings_from(schema: type, values: dict, prefix: str, owner: str):
    """The settings of `owner` (e.g. an algorithm) in the dataclass `schema`, from a plain mapping (`values`, its
    section of the config, whose keys are named `prefix`key): the defaults with `values` merged over them and
    converted as every config key is; a key `schema` lacks is refused naming the ones it has."""
    known = _fields(schema)
    for key in values:
        if key not in known:
            hint = difflib.get_close_matches(str(key), known, n=1)
            raise ConfigError(
                f"{prefix}{key} is not a setting of {owner}" + (f" (did you mean {prefix}{hint[0]}?)" if hint else "")
                + (f"; its settings: {', '.join(known)}" if known else ", which has no settings of its own")
            )
    merged = merge_layer(schema, OmegaConf.structured(structured_schema(schema)), values, "the config", prefix)
    settings = build_config(schema, OmegaConf.to_container(merged))
    _check_types(settings, prefix)
    return settings


__all__ = [
    "ConfigError",
    "DeviceConfig",
    "EvalConfig",
    "TrainConfig",
    "build_config",
    "check_device",
    "config_keys",
    "is_config_key",
    "merge_layer",
    "option",
    "settings_from",
    "structured_schema",
    "type_name",
    "unknown_key",
]
