"""What a command's config is: one dataclass per command, every field with its one-line meaning, and the checks.

Two schemas: `TrainConfig` (a training run) and `EvalConfig` (an evaluation of trained teams). A training config
has two sections: `runtime` (`RuntimeConfig`: how the run uses the machine, not part of what the run is; an
evaluation's `runtime` is its device and threads, `DeviceConfig`) and `algorithm_config` (the algorithm's own
settings, which its class reads into a dataclass of its own with `settings_from`,
`trainers.algorithms.Algorithm.Settings`); their keys are `runtime.threads`, `algorithm_config.partner_epsilon`.
Values become a checked dataclass layer by layer (`merge_layer`, then `build_config`): OmegaConf merges and converts
them over structured configs built from the dataclasses (`structured_schema`), unknown keys and ill-typed values are
refused with the valid keys, and `check()` refuses values no run can use before any work starts, with one line (a
`ConfigError`) that says what to change. How the layers come from files and the command line: `trainers.config.compose`.
"""

from __future__ import annotations

import dataclasses
import random
import typing
from dataclasses import dataclass
from pathlib import Path

from jax_env import classify_layout, load_layout
from jax_env.generator import NUM_HELDOUT_GENERATED, GeneratorConfig
from jax_env.generator import SIZES as GENERATOR_SIZES
from torch_kitchen.partners.conventions import STRANGER, TRAIN, ZOO_FILE, Convention, ConventionError, load_zoo
from trainers.config.schema import ConfigError, at_least, check_name, check_seed, check_types, option
from trainers.config.sections import DistillConfig, PPOConfig, RuntimeConfig, sectioned_keys

LOGGERS = ("tensorboard", "csv", "wandb", "mlflow", "trackio")  # TorchRL's `get_logger` backends
PLANNER_START = "scripted_cook"  # init_from: start from the scripted cook, distilled into the run's folder
GENERATED_LEVELS = ("infinite", "heldout")  # `levels` values that name generated levels rather than layouts


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
    ppo: PPOConfig = option(
        PPOConfig(), "the PPO core's settings: its Adam, its epochs and minibatches, its returns and losses, and the "
                     "shaped reward it optimises (the paper's IPPO: configs/algorithm/ippo.yaml)", group="PPO"
    )

    # --- planner-guided start (kitchen-distill, then init_from)
    init_from: str = option(
        "", f'"{PLANNER_START}": distil the scripted cook first (kitchen-distill, into RUN/distilled) and start '
            "from it; or a run directory whose latest checkpoint's weights start this run, e.g. one kitchen-distill "
            "wrote ({seed} stands for the team's seed); empty: start from scratch",
        group="planner-guided start (kitchen-distill, then init_from)",
    )
    distill: DistillConfig = option(
        DistillConfig(), "kitchen-distill: the scripted cook (or the zoo's teachers) distilled by DAgger, the start "
                         "that init_from=scripted_cook trains from"
    )
    zoo: str = option(
        ZOO_FILE, "the zoo file (kitchen-zoo) whose training conventions distill.teachers and algorithm zoo_ippo name"
    )
    learned_stranger: bool = option(
        False, "a learned stranger: distill.teachers name the zoo's held-out strangers, and the run is an evaluation "
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
        return self.num_envs // self.ppo.minibatches

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
        predates are not compared; the PPO and distillation sections' are compared one by one (`ppo.lr`)."""
        asked = learning_keys(self.identity())
        return {key: (value, asked[key]) for key, value in learning_keys(trained).items()
                if key in asked and key not in resumable and value != asked[key]}

    @property
    def generator(self) -> GeneratorConfig:
        """The Infinite Kitchen generator's config that the environment keys name."""
        return GeneratorConfig(size=self.kitchen_size, p_smaller=self.smaller_kitchens, p_wall_intact=self.intact_walls)

    def distill_teacher(self, round_: int = 0) -> Convention:
        """The convention distillation learns from in DAgger round `round_` (and kickstarted IPPO all through): the
        scripted cook with `distill.move_order`, or of `distill.teachers` the seed's (mix "seed") or one drawn by
        seed and round (mix "round")."""
        if not self.distill.teachers:
            return Convention(move_order=self.distill.move_order)
        names = self.distill.teachers
        if self.distill.teacher_mix == "seed":
            name = names[self.seed % len(names)]
        else:
            name = names[random.Random(f"{self.seed}/{round_}").randrange(len(names))]
        return load_zoo(self.zoo, self.kitchen_size).convention(name, splits=self.teacher_splits)

    @property
    def teacher_splits(self) -> tuple[str, ...]:
        """The zoo's split `distill.teachers` name: its strangers for a learned stranger, else its training split."""
        return (STRANGER,) if self.learned_stranger else (TRAIN,)

    def check(self) -> TrainConfig:
        """Refuses values no run can use, before any work starts. Touches neither the file system nor the levels:
        the trainer also calls `check_run_location` and `check_levels`; nor the algorithm's own settings, which
        it checks (`trainers.algorithms.check_algorithm`: the registry is the algorithms' own)."""
        check_types(self)
        check_name(self.name)
        check_seed(self.seed)
        at_least(self, ["max_steps", "num_envs", "rollout_steps", "total_steps", "hidden", "checkpoint_every"], 1)
        at_least(self, ["eval_episodes", "snapshots"], 0)
        self.ppo.check()
        self.distill.check()
        self.check_teachers()
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
        if self.num_envs % self.ppo.minibatches:
            raise ConfigError(
                f"ppo.minibatches ({self.ppo.minibatches}) must divide num_envs ({self.num_envs}): minibatches are "
                "whole kitchens' sequences"
            )
        self.runtime.check(self.seed, self.kitchens_per_minibatch)
        return self

    def check_teachers(self) -> None:
        """Refuses teachers the zoo does not hold in the split this run may learn from (`teacher_splits`)."""
        if self.learned_stranger and not self.distill.teachers:
            raise ConfigError("learned_stranger distils from held-out strangers: name them in distill.teachers")
        try:
            zoo = load_zoo(self.zoo, self.kitchen_size) if self.distill.teachers else None
            for name in self.distill.teachers:
                zoo.convention(name, splits=self.teacher_splits)
        except ConventionError as error:
            raise ConfigError(f"distill.teachers: {error}") from None

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


SPREAD = ("ppo", "distill")  # the sections a resume compares key by key


def learning_keys(values: dict) -> dict:
    """A run's identity (its checkpoint's config) with the PPO and distillation sections spread into their keys
    (`ppo.lr`, `distill.rounds`), a checkpoint of before those sections read into them."""
    values = sectioned_keys(values)
    spread = {key: value for key, value in values.items() if key not in SPREAD}
    for section in SPREAD:
        spread.update({f"{section}.{key}": value for key, value in (values.get(section) or {}).items()})
    return spread
