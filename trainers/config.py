"""Experiment configs: one dataclass, YAML files that mirror it, and `key=value` overrides on top.

A YAML file may name a `base:` file (relative to itself) whose values it overrides, so the configs of one
family share their common part. Unknown keys and ill-typed values are refused with the list of valid keys.
"""

from __future__ import annotations

import dataclasses
import difflib
import typing
from dataclasses import dataclass
from pathlib import Path

import yaml


class ConfigError(ValueError):
    """A config file or override that cannot be used; the message says what to change."""


@dataclass
class TrainConfig:
    """Everything an IPPO self-play run depends on. Defaults: the paper's Infinite Kitchen setting with an MLP."""

    # --- run
    name: str = "ippo_mlp_ik"  # the run directory is {run_dir}/{name}/seed{seed}
    run_dir: str = "runs"
    seed: int = 0  # seeds torch, the levels and the resets; the 6 teams of a condition are seeds 0..5
    device: str = "cpu"  # "cpu" or "cuda[:i]"; the env and the networks share it
    threads: int = 1  # torch CPU threads (1 is fastest for small networks on a shared CPU)

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
        if self.num_envs % self.minibatches:
            raise ConfigError(
                f"minibatches ({self.minibatches}) must divide num_envs ({self.num_envs}): minibatches are whole "
                "kitchens' sequences"
            )
        return self


FIELDS = {f.name: f for f in dataclasses.fields(TrainConfig)}
_TYPES = typing.get_type_hints(TrainConfig)


def _coerce(key: str, value, source: str):
    """`value` as the type of field `key`, or a ConfigError naming the field, the type and where it came from."""
    expected = _TYPES[key]
    if expected in (int, float) and isinstance(value, str):
        try:  # YAML reads 1e-3 (no dot) as a string
            value = float(value)
        except ValueError:
            pass
    if expected is bool:
        if isinstance(value, bool):
            return value
    elif expected is int:
        if isinstance(value, int) and not isinstance(value, bool):
            return value
        if isinstance(value, float) and value.is_integer():  # 2e6 in YAML is a float
            return int(value)
    elif expected is float:
        if isinstance(value, int | float) and not isinstance(value, bool):
            return float(value)
    elif expected is str:
        if isinstance(value, str):
            return value
    else:  # levels: a name, or a list of names
        if isinstance(value, str) or (isinstance(value, list) and value and all(isinstance(v, str) for v in value)):
            return value
    raise ConfigError(f"{key} in {source} must be {_type_name(expected)}, got {value!r}")


def _type_name(expected) -> str:
    return getattr(expected, "__name__", None) or str(expected).replace("typing.", "")


def _unknown_key(key: str, source: str) -> ConfigError:
    hint = difflib.get_close_matches(key, FIELDS, n=1)
    did_you_mean = f" (did you mean {hint[0]!r}?)" if hint else ""
    return ConfigError(f"unknown config key {key!r} in {source}{did_you_mean}; valid keys: {', '.join(FIELDS)}")


def _read_yaml(path: Path, seen: tuple[Path, ...] = ()) -> dict:
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
    merged = _read_yaml(path.parent / base, (*seen, path)) if base else {}
    for key, value in values.items():
        if key not in FIELDS:
            raise _unknown_key(key, str(path))
        merged[key] = (value, str(path))
    return merged


def parse_overrides(overrides: list[str]) -> dict:
    """`["lr=1e-3", "levels=[a, b]"]` -> {key: (value, source)}; values are read as YAML scalars or lists."""
    parsed = {}
    for item in overrides:
        key, sep, text = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"override {item!r} must look like key=value (e.g. seed=3)")
        key = key.strip()
        if key not in FIELDS:
            raise _unknown_key(key, "the command line")
        try:
            parsed[key] = (yaml.safe_load(text), "the command line")
        except yaml.YAMLError:
            parsed[key] = (text, "the command line")
    return parsed


def load_config(path: str | Path | None = None, overrides: list[str] = (), base: dict | None = None) -> TrainConfig:
    """A checked `TrainConfig` from defaults, then `base` (e.g. a saved run's values), the YAML file, overrides."""
    values = {key: (value, "the saved run config") for key, value in (base or {}).items()}
    for key in values:
        if key not in FIELDS:
            raise _unknown_key(key, "the saved run config")
    if path is not None:
        values.update(_read_yaml(Path(path)))
    values.update(parse_overrides(list(overrides)))
    kwargs = {key: _coerce(key, value, source) for key, (value, source) in values.items()}
    return TrainConfig(**kwargs).check()


def save_config(config: TrainConfig, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(config.to_dict(), sort_keys=False))


__all__ = ["ConfigError", "TrainConfig", "load_config", "parse_overrides", "save_config"]
