"""Experiment configs: one dataclass, YAML files that mirror it, and `key=value` overrides on top.

Two schemas: `TrainConfig` (a training run) and `EvalConfig` (an evaluation of trained teams). A YAML file may
list `defaults:` whose values it overrides, as in Hydra: files relative to itself (the common part of a family)
and config group choices (`regime: ik`, configs/regime/ik.yaml), which the command line may replace
(`regime=sk_coord_ring`). The layers (defaults, a saved run's values, the file's defaults, the file, the command
line's group choices, its overrides) are merged and
converted by OmegaConf over structured configs built from the dataclasses (`kitchen-sweep` hands the same values
to Hydra). Unknown keys and ill-typed values are refused with the list of valid keys; `check()` refuses values
no run can use before any work starts, with one line (a `ConfigError`) that says what to change. Every field
carries a one-line meaning, which `config_help` lists for `--help`.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import difflib
import functools
import math
import types
import typing
from dataclasses import dataclass
from pathlib import Path

import jax
import torch
import yaml
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException

from jax_env import EXPANDED_LAYOUTS, classify_layout, load_layout
from jax_env.generator import NUM_HELDOUT_GENERATED


class ConfigError(ValueError):
    """A config file or override that cannot be used; the message says what to change."""


LOGGERS = ("tensorboard", "csv", "wandb", "mlflow", "trackio")  # TorchRL's `get_logger` backends
PLANNER_START = "scripted_cook"  # init_from: start from the scripted cook, distilled into the run's folder
GENERATED_LEVELS = ("infinite", "heldout")  # `levels` values that name generated levels rather than layouts
# torch takes 64-bit seeds, but JAX (32-bit by default) keeps only a seed's low 32 bits: 2**32 + 5 would replay 5.
MAX_SEED = 2**32 - 1


def option(default, help: str, group: str | None = None):
    """A config field with its one-line meaning (`help`, listed by `config_help`); a list or dict default is copied
    for every instance. `group` starts a new group of keys in `config_help`."""
    metadata = {"help": help} if group is None else {"help": help, "group": group}
    if isinstance(default, list | dict):
        return dataclasses.field(default_factory=lambda: copy.deepcopy(default), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)


@dataclass
class TrainConfig:
    """Everything a self-play run (IPPO or E3T) depends on. Defaults: the paper's Infinite Kitchen setting, an MLP."""

    # --- run
    name: str = option("ippo_mlp_ik", "the run directory is {run_dir}/{name}/seed{seed}", group="run")
    run_dir: str = option("runs", "the folder that holds the runs")
    seed: int = option(0, "seeds torch, the levels and the resets; the 6 teams of a condition are seeds 0..5")
    teams: int = option(
        1, "train seeds seed .. seed+teams-1 at once, one batch of teams x num_envs kitchens; each team writes "
           "its own run directory, as a run of its own would"
    )
    device: str = option("cpu", '"cpu" or "cuda[:i]"; the env and the networks share it')
    threads: int = option(1, "torch CPU threads (1 is fastest for small networks on a shared CPU)")
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
    compile_update: bool = option(
        False, "torch.compile each PPO minibatch step (loss, backward, clipping, Adam with the learning rate a tensor) "
               "as one function; on a GPU its graphs replay as CUDA graphs; equal to eager up to float rounding"
    )

    algorithm: str = option(
        "ippo", '"ippo" (self-play), "e3t" (mixed partner + partner model; e3t_* architectures), or a registered one'
    )

    # --- environment
    levels: str | list[str] = option(
        "infinite", '"infinite" (IK), a layout name or file (SK), or a list of them', group="environment"
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

    # --- E3T (algorithm: e3t)
    partner_epsilon: float = option(
        0.3, "the mixed partner acts from (1 - eps) * pi + eps * uniform", group="E3T (algorithm: e3t)"
    )
    partner_policy: str = option("ego", 'pi of the mixed partner: "ego" (the policy itself) or "copy" (a slow copy)')
    partner_copy_rate: float = option(0.01, '"copy": after every update, copy += rate * (ego - copy)')
    predictor_coef: float = option(1.0, "weight of the partner predictor's cross-entropy in the loss")

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

    # --- logging, checkpoints, final evaluation
    checkpoint_every: int = option(
        10,
        "updates between checkpoints (one is always written at the end)",
        group="logging, checkpoints, final evaluation",
    )
    loggers: list[str] = option(
        ["tensorboard", "csv"], f"TorchRL loggers, each under the run directory: {', '.join(LOGGERS)}"
    )
    progress: bool = option(True, "a progress bar with steps/s and recent deliveries")
    eval_episodes: int = option(8, "episodes per grid in the final self-play table (0: no evaluation)")
    eval_heldout: int = option(5, "held-out generated levels in that table, beside the 5 expanded classics")
    gif: bool = option(True, "a GIF of the trained team on the first evaluation grid")

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

    def check(self) -> TrainConfig:
        """Refuses values no run can use, before any work starts. Touches neither the file system nor the levels:
        the trainer also calls `check_run_location` and `check_levels`; nor the algorithm's own settings, which
        it checks (`trainers.algorithms.check_algorithm`: the registry is the algorithms' own)."""
        _check_types(self)
        _check_name(self.name)
        _check_seed(self.seed)
        counts = ["max_steps", "num_envs", "rollout_steps", "total_steps", "hidden", "epochs", "minibatches"]
        distilling = ["distill_rounds", "distill_kitchens", "distill_epochs", "distill_minibatch"]
        _at_least(self, [*counts, "checkpoint_every", "threads", "teams", *distilling], 1)
        if self.seed + self.teams - 1 > MAX_SEED:
            raise ConfigError(f"teams={self.teams} from seed={self.seed} go past the largest seed, {MAX_SEED}")
        weights = ["entropy_coef", "value_coef", "shaping_weight"]
        _at_least(self, ["eval_episodes", "shaping_anneal_steps", "parallel_teams", "minibatch_shards", *weights], 0)
        if sorted(self.distill_move_order) != sorted("NSEW"):
            raise ConfigError(f"distill_move_order must be a permutation of NSEW, got {self.distill_move_order!r}")
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
        if self.compile_update and self.minibatch_shards > 1:
            raise ConfigError(f"compile_update compiles a whole minibatch's step: minibatch_shards="
                              f"{self.minibatch_shards} splits it; set minibatch_shards=1 (or 0)")
        if self.minibatch_shards > 1:
            if self.kitchens_per_minibatch % self.minibatch_shards:
                raise ConfigError(
                    f"minibatch_shards ({self.minibatch_shards}) must divide the {self.kitchens_per_minibatch} "
                    "kitchens of a minibatch (num_envs / minibatches): shards are equal parts"
                )
        check_device(self.device)
        return self

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

    # --- where and how long
    layouts: list[str] = option(
        list(EXPANDED_LAYOUTS), "test grids: layout names or text-grid files", group="where and how long"
    )
    heldout: int = option(NUM_HELDOUT_GENERATED, "the first N of the 100 held-out generated levels")
    rollouts: int = option(100, "episodes per pair and grid, actions sampled")
    max_steps: int = option(256, "episode length")

    # --- execution
    max_envs: int = option(
        8192, "kitchens stepped together (pairs x rollouts x grids are cut into batches of this)", group="execution"
    )
    seed: int = option(0, "the same seed gives the same numbers")
    device: str = option("cpu", '"cpu" or "cuda[:i]"')
    threads: int = option(1, "torch CPU threads")
    progress: bool = option(True, "a progress bar")

    # --- outputs
    out_dir: str = option("results/eval", "the folder of the tables, figures and GIFs", group="outputs")
    gifs: list[str] = option([], '"cond/seed0+cond/seed1@grid": agent 0, agent 1, grid')
    heatmaps: list[str] = option([], "grids on which to draw the cells agents visit")

    def check(self) -> EvalConfig:
        """Refuses values no evaluation can use, before any work starts."""
        _check_types(self)
        _check_seed(self.seed)
        _at_least(self, ["rollouts", "max_steps", "max_envs", "threads"], 1)
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
        check_device(self.device)
        return self


def check_device(device: str) -> None:
    """Refuses a device other than the CPU or a CUDA GPU that both torch and JAX see on this machine."""
    allowed = "use device=cpu, device=cuda or device=cuda:<index>"
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError, ValueError):
        raise ConfigError(f"device={device} is not a device: {allowed}") from None
    if parsed.type == "cpu" and not parsed.index:
        return
    if parsed.type != "cuda":
        raise ConfigError(f"device={device} is not supported: {allowed}")
    if not torch.cuda.is_available():
        raise ConfigError(f"device={device}, but torch sees no CUDA GPU on this machine: use device=cpu")
    index, count = parsed.index or 0, torch.cuda.device_count()
    if index >= count:
        raise ConfigError(f"device={device}, but torch sees {count} CUDA GPU(s) here: use cuda:0 to cuda:{count - 1}")
    try:  # the env runs in JAX on the same GPU (torch_kitchen.env.jax_device_for)
        jax_gpus = len(jax.devices("gpu"))
    except RuntimeError:
        jax_gpus = 0
    if index >= jax_gpus:
        raise ConfigError(
            f"device={device}, but JAX sees {jax_gpus} GPU(s) here (backend: {jax.default_backend()}): install a CUDA "
            'build of JAX matching the driver (pip install -U "jax[cuda12]") or use device=cpu'
        )


def train_config_parser(prog: str, description: str) -> argparse.ArgumentParser:
    """The command line of a command that reads a training config: a YAML file (omitted with --resume) and
    key=value overrides, every key with its meaning under --help (`config_help`)."""
    parser = argparse.ArgumentParser(
        prog=prog, description=f"{description} Overrides: any config key as key=value (e.g. seed=3 total_steps=2e6).",
        epilog=config_help(TrainConfig), formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("config", nargs="?", help="a YAML config (configs/...); omit it with --resume")
    parser.add_argument("overrides", nargs="*", help="key=value config overrides")
    return parser


def config_help(schema: type) -> str:
    """Every key of `schema` with its type, default and meaning, in groups: an argparse epilog (to be shown with
    `argparse.RawDescriptionHelpFormatter`, which keeps its lines)."""
    hints = typing.get_type_hints(schema)
    lines = ["config keys (in the YAML file, or as key=value overrides):"]
    for field in dataclasses.fields(schema):
        if "group" in field.metadata:
            lines += ["", f"  {field.metadata['group']}:"]
        default = field.default_factory() if field.default is dataclasses.MISSING else field.default
        lines.append(f"    {field.name}: {_type_name(hints[field.name])} = {_yaml_scalar(default)}")
        lines.append(f"        {field.metadata['help']}")
    if schema is TrainConfig:
        lines += ["", "config groups (in a file's `defaults:` list, or as group=choice, which replaces the file's):"]
        for group, meaning in GROUPS.items():
            lines += [f"    {group}: {' | '.join(group_choices(group))}", f"        {meaning}"]
    return "\n".join(lines)


def _yaml_scalar(value) -> str:
    """A value as one line of YAML, as it would be written in an override."""
    return yaml.safe_dump(value, default_flow_style=True, width=math.inf).removesuffix("\n...\n").strip()


def _check_types(config: TrainConfig | EvalConfig) -> None:
    """Refuses a field whose value does not fit its type (a config built in Python skips `_merge`)."""
    hints = typing.get_type_hints(type(config))
    for field in dataclasses.fields(config):
        value, expected = getattr(config, field.name), hints[field.name]
        if not _matches(value, expected):
            raise ConfigError(f"{field.name} must be {_type_name(expected)}, got {value!r}")
        if expected is float and not math.isfinite(value):  # YAML reads .inf and .nan, float() reads "nan"
            raise ConfigError(f"{field.name} must be a finite number, got {value}")


def _at_least(config: TrainConfig | EvalConfig, names: list[str], low: int) -> None:
    for name in names:
        if not getattr(config, name) >= low:
            raise ConfigError(f"{name} must be at least {low}, got {getattr(config, name)}")


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


def _type_name(expected) -> str:
    if typing.get_origin(expected) is None:
        return expected.__name__
    return str(expected).replace("typing.", "")


def unknown_key(schema: type, key: str, source: str) -> ConfigError:
    hint = difflib.get_close_matches(key, _fields(schema), n=1)
    did_you_mean = f" (did you mean {hint[0]!r}?)" if hint else ""
    return ConfigError(f"unknown config key {key!r} in {source}{did_you_mean}; valid keys: {_key_list(schema)}")


def _key_list(schema: type) -> str:
    return ", ".join(_fields(schema))


# ------------------------------------------------------------------------------- merging, on OmegaConf
def _is_union(expected) -> bool:
    return typing.get_origin(expected) in (typing.Union, types.UnionType)


def _omegaconf_type(expected):
    """A field type as OmegaConf can hold it: it types no unions (`levels: str | list[str]`), so those are Any
    there and `_merge` checks them."""
    origin, args = typing.get_origin(expected), typing.get_args(expected)
    if _is_union(expected):
        return typing.Any
    if origin is list:
        return list[_omegaconf_type(args[0])]
    if origin is dict:
        return dict[args[0], _omegaconf_type(args[1])]
    return expected


@functools.cache
def _structured(schema: type) -> type:
    """`schema` as a dataclass OmegaConf can type: the same fields and defaults, unions as Any."""
    hints = typing.get_type_hints(schema)
    fields = [(field.name, _omegaconf_type(hints[field.name]),
               dataclasses.field(default=field.default, default_factory=field.default_factory))
              for field in dataclasses.fields(schema)]  # fmt: skip
    return dataclasses.make_dataclass(schema.__name__, fields)


def _merge(schema: type, merged: DictConfig, values: dict, source: str) -> DictConfig:
    """`values` (from `source`: a file, the command line, a saved run) merged over `merged` by OmegaConf, which
    converts what it can (e.g. "1e-3" to a float); a ConfigError names the key, its type and the source."""
    hints = typing.get_type_hints(schema)
    layer = {}
    for key, value in values.items():
        if key not in hints:
            raise unknown_key(schema, key, source)
        expected = hints[key]
        if expected is str and value is None:  # `key=` on the command line: the empty string
            value = ""
        if expected is int and isinstance(value, str | float) and not isinstance(value, bool):
            try:  # 2e6 is a float to YAML and a string to PyYAML; OmegaConf takes neither as an int
                value = int(float(value)) if float(value).is_integer() else value
            except ValueError:
                pass
        strict = _is_union(expected) or expected is bool or isinstance(value, bool)  # OmegaConf reads 3 as True
        if strict and not _matches(value, expected):
            raise ConfigError(f"{key} in {source} must be {_type_name(expected)}, got {value!r}")
        layer[key] = value
    try:
        merged = merged.copy()
        for key, value in layer.items():
            if isinstance(value, dict):
                merged[key] = {}  # a later layer replaces a mapping, as it replaces any value, instead of merging
        return OmegaConf.merge(merged, layer)
    except OmegaConfBaseException as error:
        key = str(getattr(error, "full_key", "") or "").split(".")[0] or next(iter(layer))
        raise ConfigError(
            f"{key} in {source} must be {_type_name(hints.get(key, object))}, got {layer.get(key)!r}"
        ) from None


CONFIG_ROOT = Path(__file__).resolve().parent.parent / "configs"  # the shipped configs, and the config groups
# Config groups, as in Hydra: configs/<group>/<choice>.yaml, chosen in a file's `defaults:` list (`- regime: ik`)
# or on the command line (`regime=sk_coord_ring`, which replaces the file's choice and comes after the file).
GROUPS = {"regime": "the paper's training regime: ik (Infinite Kitchen) or sk_<layout> (Single Kitchen)"}


@dataclass
class Layer:
    """Values to merge, where they come from, and the config group they were chosen from (None: not a group's)."""

    values: dict
    source: str
    group: str | None = None


def group_choices(group: str) -> list[str]:
    """The choices of a config group: the names of configs/<group>/*.yaml."""
    return sorted(path.stem for path in (CONFIG_ROOT / group).glob("*.yaml"))


def group_values(group: str, choice: str) -> dict:
    """The values that `choice` of a config group sets (its file, its own defaults first)."""
    values = {}
    for layer in _group_layers(TrainConfig, group, choice, "the config group"):
        values.update(layer.values)
    return values


def _group_layers(schema: type, group: str, choice, source: str) -> list[Layer]:
    """The layers of `choice` in `group`, or a ConfigError naming the choices."""
    if not isinstance(choice, str) or choice not in group_choices(group):
        raise ConfigError(f"{group} in {source} must be one of {', '.join(group_choices(group))}, got {choice!r}")
    return [dataclasses.replace(layer, group=group)
            for layer in _read_yaml(schema, CONFIG_ROOT / group / f"{choice}.yaml")]


def _read_yaml(schema: type, path: Path, seen: tuple[Path, ...] = ()) -> list[Layer]:
    """The layers of a YAML config: those of its `defaults:` list in order (files relative to it, and config group
    choices such as `regime: ik`), then the file's own. `base: FILE` is the same as `defaults: [FILE]`."""
    path = path.resolve()
    if path in seen:
        raise ConfigError(f"config {path} names itself as a base (through {' -> '.join(map(str, seen))})")
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    try:
        values = yaml.safe_load(path.read_text()) or {}
    except (yaml.YAMLError, UnicodeDecodeError) as error:
        raise ConfigError(f"config file {path} is not valid YAML: {error}") from None
    if not isinstance(values, dict):
        raise ConfigError(f"config file {path} must hold `key: value` lines, got {type(values).__name__}")
    for key in values:
        if not isinstance(key, str):
            raise ConfigError(
                f"the key {key!r} in {path} is not a config key (keys are names): valid keys: {_key_list(schema)}"
            )
    defaults = values.pop("defaults", [])
    if "base" in values:
        base = values.pop("base")
        if not isinstance(base, str) or not base.strip():
            raise ConfigError(f"base in {path} must be the path of a config file (relative to this one), got {base!r}")
        defaults = [base, *defaults] if isinstance(defaults, list) else defaults
    if not isinstance(defaults, list):
        raise ConfigError(f"defaults in {path} must be a list of files and choices (e.g. [base.yaml, regime: ik])")
    layers = []
    for item in defaults:
        if isinstance(item, str) and item.strip():
            layers += _read_yaml(schema, path.parent / item, (*seen, path))
        elif isinstance(item, dict) and len(item) == 1 and next(iter(item)) in GROUPS:
            (group, choice), = item.items()
            layers += _group_layers(schema, group, choice, str(path))
        else:
            raise ConfigError(f"defaults in {path}: {item!r} is neither a config file (relative to this one) nor a "
                              f"group choice ({', '.join(f'{group}: <choice>' for group in GROUPS)})")
    return [*layers, Layer(values, str(path))]


def parse_overrides(overrides: list[str], schema: type = TrainConfig) -> dict:
    """`["lr=1e-3", "levels=[a, b]"]` -> {key: value}, each value read by OmegaConf's dotlist grammar (YAML)."""
    parsed = {}
    for item in overrides:
        key, sep, _ = item.partition("=")
        if not sep or not key.strip():
            raise ConfigError(f"override {item!r} must look like key=value (e.g. seed=3)")
        if key.strip() not in _fields(schema):
            raise unknown_key(schema, key.strip(), "the command line")
        try:
            parsed.update(OmegaConf.to_container(OmegaConf.from_dotlist([item.strip()])))
        except OmegaConfBaseException:
            parsed[key.strip()] = item.partition("=")[2]
    return parsed


Config = typing.TypeVar("Config", TrainConfig, EvalConfig)


def load_config(
    path: str | Path | None = None,
    overrides: list[str] = (),
    base: dict | None = None,
    schema: type[Config] = TrainConfig,
) -> Config:
    """A checked `schema` config: its defaults, then `base` (e.g. a saved run's values), the YAML file (its
    `defaults:` first), the command line's group choices (`regime=ik`, replacing the file's), then its `key=value`
    overrides, merged in that order by OmegaConf."""
    choices = {item.partition("=")[0].strip(): item.partition("=")[2].strip() for item in overrides
               if schema is TrainConfig and item.partition("=")[0].strip() in GROUPS}
    layers = [Layer(base or {}, "the saved run config")]
    if path is not None:
        layers += [layer for layer in _read_yaml(schema, Path(path)) if layer.group not in choices]
    for group, choice in choices.items():
        layers += _group_layers(schema, group, choice, "the command line")
    keys = [item for item in overrides if item.partition("=")[0].strip() not in choices]
    layers.append(Layer(parse_overrides(keys, schema), "the command line"))
    merged = OmegaConf.structured(_structured(schema))
    for layer in layers:
        merged = _merge(schema, merged, layer.values, layer.source)
    return schema(**OmegaConf.to_container(merged)).check()


def save_config(config: TrainConfig | EvalConfig, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(dataclasses.asdict(config), sort_keys=False))


__all__ = [
    "ConfigError",
    "EvalConfig",
    "TrainConfig",
    "check_device",
    "config_help",
    "group_choices",
    "group_values",
    "load_config",
    "option",
    "parse_overrides",
    "save_config",
    "train_config_parser",
    "unknown_key",
]
