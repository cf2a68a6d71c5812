"""Experiment configs: one dataclass, YAML files that mirror it, and `key=value` overrides on top.

Two schemas: `TrainConfig` (a training run) and `EvalConfig` (an evaluation of trained teams). A YAML file may
name a `base:` file (relative to itself) whose values it overrides, so the configs of one family share their
common part. Unknown keys and ill-typed values are refused with the list of valid keys.
"""

from __future__ import annotations

import dataclasses
import difflib
import types
import typing
from dataclasses import dataclass
from pathlib import Path

import yaml

from jax_env import EXPANDED_LAYOUTS


class ConfigError(ValueError):
    """A config file or override that cannot be used; the message says what to change."""


ALGORITHMS = ("ippo", "e3t")
PARTNER_POLICIES = ("ego", "copy")


@dataclass
class TrainConfig:
    """Everything a self-play run (IPPO or E3T) depends on. Defaults: the paper's Infinite Kitchen setting with an MLP."""

    # --- run
    name: str = "ippo_mlp_ik"  # the run directory is {run_dir}/{name}/seed{seed}
    run_dir: str = "runs"
    seed: int = 0  # seeds torch, the levels and the resets; the 6 teams of a condition are seeds 0..5
    device: str = "cpu"  # "cpu" or "cuda[:i]"; the env and the networks share it
    threads: int = 1  # torch CPU threads (1 is fastest for small networks on a shared CPU)

    algorithm: str = "ippo"  # "ippo" (self-play) or "e3t" (mixed partner + partner model; e3t_* architectures)

    # --- environment
    levels: str | list[str] = "infinite"  # "infinite" (IK), a layout name or file (SK), or a list of them
    max_steps: int = 256  # episode length
    num_envs: int = 32  # kitchens stepped together
    rollout_steps: int = 256  # steps of every kitchen per update (one full episode by default)
    total_steps: int = 20_000_000  # env steps over the run (num_envs x rollout_steps per update)

    # --- model
    architecture: str = "mlp"  # mlp | mlp_lstm | gnn | gnn_lstm, or a name given to register_architecture
    hidden: int = 256  # 256 for IK, 128 for SK in the paper
    share_params: bool = True  # one network for both agents (IK) or one per agent (SK)

    # --- PPO
    lr: float = 2.5e-4
    anneal_lr: bool = True  # linearly to 0 over the run
    adam_eps: float = 1e-5
    epochs: int = 4  # passes over each batch
    minibatches: int = 4  # split over kitchens, so every minibatch holds whole sequences (for recurrent models)
    gamma: float = 0.99
    gae_lambda: float = 0.95
    clip_epsilon: float = 0.2  # for the policy ratio and the value
    entropy_coef: float = 0.01
    value_coef: float = 0.5
    max_grad_norm: float = 0.5
    shaping_weight: float = 0.0  # weight of the shaped reward added to the sparse one (0: sparse only)
    shaping_anneal_steps: int = 0  # anneal shaping_weight linearly to 0 over this many env steps (0: constant)

    # --- E3T (algorithm: e3t)
    partner_epsilon: float = 0.3  # the mixed partner acts from (1 - eps) * pi + eps * uniform
    partner_policy: str = "ego"  # pi of the mixed partner: "ego" (the policy itself) or "copy" (a slow copy)
    partner_copy_rate: float = 0.01  # "copy": after every update, copy += rate * (ego - copy)
    predictor_coef: float = 1.0  # weight of the partner predictor's cross-entropy in the loss

    # --- logging, checkpoints, final evaluation
    checkpoint_every: int = 10  # updates between checkpoints (one is always written at the end)
    progress: bool = True  # a progress bar with steps/s and recent deliveries
    eval_episodes: int = 8  # episodes per grid in the final self-play table (0: no evaluation)
    eval_heldout: int = 5  # held-out generated levels in that table, beside the 5 expanded classics
    gif: bool = True  # a GIF of the trained team on the first evaluation grid

    @property
    def run_path(self) -> Path:
        return Path(self.run_dir) / self.name / f"seed{self.seed}"

    @property
    def frames_per_batch(self) -> int:
        return self.num_envs * self.rollout_steps

    @property
    def num_updates(self) -> int:
        return max(1, self.total_steps // self.frames_per_batch)

    def to_dict(self) -> dict:
        return dataclasses.asdict(self)

    def check(self) -> TrainConfig:
        """Refuses values no run can use, before any work starts."""
        positive = ["max_steps", "num_envs", "rollout_steps", "total_steps", "hidden", "epochs", "minibatches"]
        for name in positive:
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be at least 1, got {getattr(self, name)}")
        if not self.levels:
            raise ConfigError("levels is empty: give a layout name or file, a list of them, or 'infinite'")
        if self.algorithm not in ALGORITHMS:
            raise ConfigError(f"algorithm must be one of {', '.join(ALGORITHMS)}, got {self.algorithm!r}")
        if self.partner_policy not in PARTNER_POLICIES:
            raise ConfigError(
                f"partner_policy must be one of {', '.join(PARTNER_POLICIES)}, got {self.partner_policy!r}"
            )
        for name in ("partner_epsilon", "partner_copy_rate"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ConfigError(f"{name} must lie in [0, 1], got {getattr(self, name)}")
        if self.num_envs % self.minibatches:
            raise ConfigError(
                f"minibatches ({self.minibatches}) must divide num_envs ({self.num_envs}): minibatches are whole "
                "kitchens' sequences"
            )
        return self


@dataclass
class EvalConfig:
    """The self-play / cross-play evaluation of populations of trained teams (`kitchen-eval`).

    Every ordered pair of teams within a condition plays (i == j: self-play, i != j: cross-play), and so does
    every pair across the conditions named in `cross`; each pair plays `rollouts` episodes on every test grid.
    """

    # --- who plays
    conditions: dict[str, str | list[str]] = dataclasses.field(default_factory=dict)  # name -> run dirs or globs
    cross: list[list[str]] = dataclasses.field(default_factory=list)  # [[cond_a, cond_b], ...] to cross-play

    # --- where and how long
    layouts: list[str] = dataclasses.field(default_factory=lambda: list(EXPANDED_LAYOUTS))
    heldout: int = 100  # the first N of the 100 held-out generated levels
    rollouts: int = 100  # episodes per pair and grid, actions sampled
    max_steps: int = 256

    # --- execution
    max_envs: int = 8192  # kitchens stepped together (pairs x rollouts x grids are cut into batches of this)
    seed: int = 0  # the same seed gives the same numbers
    device: str = "cpu"
    threads: int = 1
    progress: bool = True

    # --- outputs
    out_dir: str = "results/eval"
    gifs: list[str] = dataclasses.field(default_factory=list)  # "cond/seed0+cond/seed1@grid": agent 0, agent 1, grid
    heatmaps: list[str] = dataclasses.field(default_factory=list)  # grids on which to draw the cells agents visit

    def check(self) -> EvalConfig:
        for name in ("rollouts", "max_steps", "max_envs"):
            if getattr(self, name) < 1:
                raise ConfigError(f"{name} must be at least 1, got {getattr(self, name)}")
        if not 0 <= self.heldout <= 100:
            raise ConfigError(f"heldout must be between 0 and 100 (the held-out levels), got {self.heldout}")
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
        return self


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


def _coerce(schema: type, key: str, value, source: str):
    """`value` as the type of field `key`, or a ConfigError naming the field, the type and where it came from."""
    expected = typing.get_type_hints(schema)[key]
    if expected in (int, float) and isinstance(value, str):
        try:  # YAML reads 1e-3 (no dot) as a string
            value = float(value)
        except ValueError:
            pass
    if expected is int and isinstance(value, float) and value.is_integer():  # 2e6 in YAML is a float
        value = int(value)
    if _matches(value, expected):
        return float(value) if expected is float else value
    raise ConfigError(f"{key} in {source} must be {_type_name(expected)}, got {value!r}")


def _type_name(expected) -> str:
    if typing.get_origin(expected) is None:
        return expected.__name__
    return str(expected).replace("typing.", "")


def _unknown_key(schema: type, key: str, source: str) -> ConfigError:
    fields = _fields(schema)
    hint = difflib.get_close_matches(key, fields, n=1)
    did_you_mean = f" (did you mean {hint[0]!r}?)" if hint else ""
    return ConfigError(f"unknown config key {key!r} in {source}{did_you_mean}; valid keys: {', '.join(fields)}")


def _read_yaml(schema: type, path: Path, seen: tuple[Path, ...] = ()) -> dict:
    """The values of a YAML config and of its `base:` chain, the file's own values last."""
    path = path.resolve()
    if path in seen:
        raise ConfigError(f"config {path} names itself as a base (through {' -> '.join(map(str, seen))})")
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    try:
        values = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as error:
        raise ConfigError(f"config file {path} is not valid YAML: {error}") from None
    if not isinstance(values, dict):
        raise ConfigError(f"config file {path} must hold `key: value` lines, got {type(values).__name__}")
    base = values.pop("base", None)
    merged = _read_yaml(schema, path.parent / base, (*seen, path)) if base else {}
    for key, value in values.items():
        if key not in _fields(schema):
            raise _unknown_key(schema, key, str(path))
        merged[key] = (value, str(path))
    return merged


def parse_overrides(overrides: list[str], schema: type = TrainConfig) -> dict:
    """`["lr=1e-3", "levels=[a, b]"]` -> {key: (value, source)}; values are read as YAML scalars or lists."""
    parsed = {}
    for item in overrides:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"override {item!r} must look like key=value (e.g. seed=3)")
        key = key.strip()
        if key not in _fields(schema):
            raise _unknown_key(schema, key, "the command line")
        try:
            parsed[key] = (yaml.safe_load(text), "the command line")
        except yaml.YAMLError:
            parsed[key] = (text, "the command line")
    return parsed


Config = typing.TypeVar("Config", TrainConfig, EvalConfig)


def load_config(
    path: str | Path | None = None,
    overrides: list[str] = (),
    base: dict | None = None,
    schema: type[Config] = TrainConfig,
) -> Config:
    """A checked `schema` config from defaults, then `base` (e.g. a saved run's values), the YAML file, overrides."""
    values = {key: (value, "the saved run config") for key, value in (base or {}).items()}
    for key in values:
        if key not in _fields(schema):
            raise _unknown_key(schema, key, "the saved run config")
    if path is not None:
        values.update(_read_yaml(schema, Path(path)))
    values.update(parse_overrides(list(overrides), schema))
    kwargs = {key: _coerce(schema, key, value, source) for key, (value, source) in values.items()}
    return schema(**kwargs).check()


def save_config(config: TrainConfig | EvalConfig, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(dataclasses.asdict(config), sort_keys=False))


__all__ = ["ConfigError", "EvalConfig", "TrainConfig", "load_config", "parse_overrides", "save_config"]
