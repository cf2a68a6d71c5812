"""How a command's config is built: Hydra composes a YAML file with the config groups of configs/, the command
line's `key=value` overrides go on top, and the result is checked as `trainers.config`'s dataclasses say.

Every command's file goes through Hydra's compose API (`compose`): its `defaults:` list (files beside it, and the
config groups of configs/: `algorithm`, `architecture`, `regime`, `runtime`, chosen as `- /regime: ik`), then the
file's own values; a group chosen on the command line (`regime=sk_coord_ring`) takes the file's choice's place, and
`kitchen-sweep` sweeps the same groups over the same files. The layers (the schema's defaults, a saved run's values,
the composed file, the command line's keys) are merged and converted by OmegaConf (`trainers.config.merge_layer`);
Hydra's own composition errors become one line naming the file. Configs and saved runs from before the `runtime`,
`ppo`, `distill` and `algorithm_config` sections are read into them (`sectioned`). `config_help` lists every key and
group for `--help`.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import dataclasses
import functools
import math
import typing
import warnings
from collections.abc import Sequence
from pathlib import Path

import yaml
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from trainers.config import (
    ConfigError,
    DeviceConfig,
    EvalConfig,
    RuntimeConfig,
    TrainConfig,
    build_config,
    config_keys,
    is_config_key,
    merge_layer,
    sectioned_keys,
    structured_schema,
    type_name,
    unknown_key,
)


def train_config_parser(prog: str, description: str, sections: dict[str, type] | None = None
                        ) -> argparse.ArgumentParser:
    """The command line of a command that reads a training config: a YAML file (omitted with --resume) and
    key=value overrides, every key with its meaning under --help (`config_help`, with the algorithms' `sections`)."""
    parser = argparse.ArgumentParser(
        prog=prog, description=f"{description} Overrides: any config key as key=value (e.g. seed=3 total_steps=2e6 "
                               "runtime.threads=2).",
        epilog=config_help(TrainConfig, sections), formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("config", nargs="?", help="a YAML config (configs/...); omit it with --resume")
    parser.add_argument("overrides", nargs="*", help="key=value config overrides")
    return parser


def config_help(schema: type, sections: dict[str, type] | None = None) -> str:
    """Every key of `schema` with its type, default and meaning, in groups, then the keys of each algorithm's own
    settings (`sections`: algorithm name -> its settings' dataclass): an argparse epilog (to be shown with
    `argparse.RawDescriptionHelpFormatter`, which keeps its lines)."""
    lines = ["config keys (in the YAML file, or as key=value overrides):", *_key_lines(schema)]
    for name, settings in (sections or {}).items():
        lines += ["", f"  algorithm_config (algorithm: {name}):", *_key_lines(settings, "algorithm_config.")]
    groups = GROUPS if schema is TrainConfig else {"runtime": GROUPS["runtime"]}
    lines += ["", "config groups (configs/<group>/; in a file's `defaults:` list as `/group: choice`, or as "
                  "group=choice, which takes the file's choice's place):"]
    for group in groups:
        lines += [f"    {group}: {' | '.join(group_choices(group))}", f"        {groups[group]}"]
    return "\n".join(lines)


def _key_lines(schema: type, prefix: str = "") -> list[str]:
    """The help lines of `schema`'s keys, named with `prefix`; a section's keys as `section.key`, under its group."""
    hints, lines = typing.get_type_hints(schema), []
    for field in dataclasses.fields(schema):
        if "group" in field.metadata:
            lines += ["", f"  {prefix}{field.metadata['group']}:"]
        if dataclasses.is_dataclass(hints[field.name]):
            lines += [f"    {prefix}{field.name}: a section of the keys below", f"        {field.metadata['help']}",
                      *_key_lines(hints[field.name], f"{prefix}{field.name}.")]
            continue
        default = field.default_factory() if field.default is dataclasses.MISSING else field.default
        lines.append(f"    {prefix}{field.name}: {type_name(hints[field.name])} = {_yaml_scalar(default)}")
        lines.append(f"        {field.metadata['help']}")
    return lines


def _yaml_scalar(value) -> str:
    """A value as one line of YAML, as it would be written in an override."""
    return yaml.safe_dump(value, default_flow_style=True, width=math.inf).removesuffix("\n...\n").strip()


# Keys that had no section before `runtime` and `algorithm_config` did, as saved runs and older files hold them
# (distillation's: `trainers.config.sections.FLAT_DISTILL_KEYS`).
RUN_OPTIONS = {schema: tuple(field.name for field in dataclasses.fields(section))
               for schema, section in ((TrainConfig, RuntimeConfig), (EvalConfig, DeviceConfig))}
E3T_SETTINGS = ("partner_epsilon", "partner_policy", "partner_copy_rate", "predictor_coef")


def sectioned(values: dict, schema: type = TrainConfig) -> dict:
    """A config's values written before the run options, PPO's settings, distillation and the algorithm's settings had
    sections, put in them: the run options under `runtime` (an evaluation's device and threads too), PPO's under
    `ppo`, distillation's under `distill`, E3T's under `algorithm_config` where the values train E3T (others ignored
    them, and a config saved by any run held them all)."""
    run_options = RUN_OPTIONS.get(schema, ())
    settings_keys = E3T_SETTINGS if schema is TrainConfig else ()
    if schema is TrainConfig:
        values = sectioned_keys(values)
    if not any(key in values for key in (*run_options, *settings_keys)):
        return values
    values = dict(values)
    runtime = {key: values.pop(key) for key in run_options if key in values}
    settings = {key: values.pop(key) for key in settings_keys if key in values}
    if runtime:
        values["runtime"] = {**runtime, **(values.get("runtime") or {})}
    if settings and values.get("algorithm", "e3t") == "e3t":
        values["algorithm_config"] = {**settings, **(values.get("algorithm_config") or {})}
    return values


CONFIG_ROOT = Path(__file__).resolve().parents[2] / "configs"  # the shipped configs, and the config groups
# Config groups (configs/<group>/<choice>.yaml), composed by Hydra: a file's `defaults:` list chooses them
# (`- /regime: ik`), and the command line replaces or adds a choice (`regime=sk_coord_ring`).
GROUPS = {
    "algorithm": "the algorithm and the paper's PPO settings: ippo, or e3t (IPPO's, with E3T's partner)",
    "architecture": "the networks: mlp, gnn, their _lstm forms, ego_mlp, e3t_mlp, e3t_gnn",
    "regime": "the paper's training regime: ik (Infinite Kitchen) or sk_<layout> (Single Kitchen)",
    "runtime": "where a command runs: cpu or gpu (device and threads, as runtime.device=, runtime.threads=)",
}


def group_choices(group: str) -> list[str]:
    """The choices of a config group: the names of configs/<group>/*.yaml."""
    return sorted(path.stem for path in (CONFIG_ROOT / group).glob("*.yaml"))


def is_group_choice(item: str) -> bool:
    """Whether a command-line `key=value` chooses from a config group (`regime=ik`, `algorithm=e3t`) rather than sets
    a key; a group that is not a key (`regime`) takes nothing else (a ConfigError names its choices)."""
    key, _, value = (part.strip() for part in item.partition("="))
    if key not in GROUPS:
        return False
    if value in group_choices(key):
        return True
    if key in config_keys(TrainConfig) or key in config_keys(EvalConfig):
        return False  # e.g. architecture=<a registered plugin's>: the key alone
    raise ConfigError(f"{key} on the command line must be one of {', '.join(group_choices(key))}, got {value!r}")


def _checked_file(path: Path, schema: type) -> None:
    """Refuses, in one line, a config file that does not exist, is not YAML or does not hold `key: value` lines."""
    if not path.is_file():
        raise ConfigError(f"config file {path} does not exist")
    try:
        values = yaml.safe_load(path.read_text()) or {}
    except (yaml.YAMLError, UnicodeDecodeError) as error:
        raise ConfigError(f"config file {path} is not valid YAML: {' '.join(str(error).split())}") from None
    if not isinstance(values, dict):
        raise ConfigError(f"config file {path} must hold `key: value` lines, got {type(values).__name__}")
    for key in values:
        if not isinstance(key, str):
            raise ConfigError(f"the key {key!r} in {path} is not a config key (keys are names): valid keys: "
                              f"{', '.join(config_keys(schema))}")
    if "base" in values:
        raise ConfigError(f"base in {path}: list the file in the defaults instead, `defaults: [{values['base']}, "
                          "_self_]` (files beside it and config group choices, as Hydra composes them)")


@contextlib.contextmanager
def _hydra_at(config_dir: Path):
    """Hydra's compose API over `config_dir`, then the shipped configs (for their groups); a Hydra app this runs
    inside (a sweep's job) gets its own state back afterwards."""
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    outer = GlobalHydra.instance().hydra if GlobalHydra.instance().is_initialized() else None
    GlobalHydra.instance().clear()
    try:
        with initialize_config_dir(config_dir=str(config_dir), version_base="1.3"):
            yield
    finally:
        if outer is not None:
            GlobalHydra.instance().initialize(outer)


def _one_line(error: Exception, where: str) -> ConfigError:
    """A Hydra composition error as one line naming the file: a missing group choice with the choices."""
    from hydra.errors import MissingConfigException

    if isinstance(error, MissingConfigException) and error.options:
        group, _, choice = str(error.missing_cfg_file).rpartition("/")
        return ConfigError(f"{group.lstrip('/')} in {where} must be one of {', '.join(error.options)}, got {choice!r}")
    if isinstance(error, MissingConfigException):
        return ConfigError(f"the defaults of {where} name {error.missing_cfg_file!r}, which is neither a config file "
                           "beside it nor a config group choice (e.g. /algorithm: ippo, /regime: ik)")
    return ConfigError(f"{where}: {str(error).strip().splitlines()[0]}")


def _hydra_compose(path: Path | None, overrides: Sequence[str], hydra_config: bool = False):
    """One call of Hydra's compose API over the file at `path` (None: an empty primary config) with configs/ on its
    search path; its errors as one line naming the file."""
    from hydra import compose as hydra_compose
    from hydra.errors import HydraException

    where = str(path) if path is not None else "the command line"
    try:
        with warnings.catch_warnings(), _hydra_at(path.parent if path is not None else CONFIG_ROOT):
            warnings.filterwarnings("ignore", message=".*Defaults list is missing `_self_`")
            return hydra_compose(config_name=path.stem if path is not None else None,
                                 overrides=[f"hydra.searchpath=[file://{CONFIG_ROOT}]", *overrides],
                                 return_hydra_config=hydra_config)
    except (HydraException, OmegaConfBaseException, yaml.YAMLError, ValueError) as error:  # ValueError: a
        raise _one_line(error, where) from None  # defaults list that is not a list
    except RecursionError:
        raise ConfigError(f"the defaults of {where} include one another in a loop") from None


def group_overrides(path: Path | None, choices: Sequence[str]) -> list[str]:
    """The command line's group `choices` as Hydra takes them over the file at `path`: `group=choice` in place of
    the file's choice, `+group=choice` where its defaults choose none of that group (Hydra's record of the file's
    choices says which)."""
    if not choices:
        return []
    chosen = set(_hydra_compose(path, [], hydra_config=True).hydra.runtime.choices) if path is not None else set()
    return [item if item.partition("=")[0].strip() in chosen else f"+{item}" for item in choices]


def compose(path: Path | None, choices: Sequence[str] = (), schema: type = TrainConfig) -> dict:
    """The values Hydra's compose API builds from the YAML file at `path` (None: none, only `choices`): its
    `defaults:` list in order (files beside it, config groups from configs/ such as `/regime: ik`), the file's own
    values after them, and the command line's group `choices` in place of the file's (or added)."""
    if path is not None:
        path = path.resolve()
        _checked_file(path, schema)
    key = (path, tuple(choices), _yaml_files_state(path))
    if key not in _COMPOSED:
        while len(_COMPOSED) >= 256:
            _COMPOSED.pop(next(iter(_COMPOSED)))
        composed = _hydra_compose(path, group_overrides(path, choices))
        _COMPOSED[key] = OmegaConf.to_container(composed, resolve=False)
    return copy.deepcopy(_COMPOSED[key])


# Compositions already made in this process (a protocol or a sweep composes the same files again and again, at 50 ms
# each), keyed by the contents of every YAML file a composition could read, so that an edited file composes anew.
_COMPOSED: dict[tuple, dict] = {}


def _yaml_files_state(path: Path | None) -> int:
    """A hash of the YAML files Hydra searches for `path`, names and contents: configs/ and its groups, the file's
    folder and that folder's sub-folders (a file's own groups)."""
    files = sorted(CONFIG_ROOT.rglob("*.yaml"))
    if path is not None and not path.is_relative_to(CONFIG_ROOT):
        files += sorted(path.parent.glob("*.yaml")) + sorted(path.parent.glob("*/*.yaml"))
    return hash(tuple((str(file), file.read_bytes()) for file in files))


def parse_overrides(overrides: list[str], schema: type = TrainConfig) -> dict:
    """`["ppo.lr=1e-3", "levels=[a, b]", "runtime.threads=2"]` -> {key: value} (a section's keys nested under it), each
    value read by OmegaConf's dotlist grammar (YAML)."""
    parsed = {}
    for item in overrides:
        key, sep, raw = (part.strip() for part in item.partition("="))
        if not sep or not key:
            raise ConfigError(f"override {item!r} must look like key=value (e.g. seed=3)")
        if not is_config_key(schema, key):
            raise unknown_key(schema, key, "the command line")
        value = copy.deepcopy(_override_value(raw))  # a list or mapping of its own for each config
        *sections, name = key.split(".")
        inner = parsed
        for section in sections:
            inner = inner.setdefault(section, {})
        inner[name] = value
    return parsed


@functools.lru_cache(maxsize=1024)
def _override_value(raw: str):
    """The value of an override's right-hand side, as OmegaConf's dotlist grammar (YAML) reads it; the text itself
    where it does not parse. Kept per text: the parser takes 2 ms a value, and a protocol passes the same ones to
    every run."""
    try:
        return OmegaConf.to_container(OmegaConf.from_dotlist([f"value={raw}"]))["value"]
    except OmegaConfBaseException:
        return raw


Config = typing.TypeVar("Config", TrainConfig, EvalConfig)


def load_config(
    path: str | Path | None = None,
    overrides: Sequence[str] = (),
    base: dict | None = None,
    schema: type[Config] = TrainConfig,
) -> Config:
    """A checked `schema` config: its defaults, then `base` (e.g. a saved run's values), the YAML file as Hydra
    composes it with the command line's group choices (`compose`), then the command line's `key=value` overrides
    (a group choice that is also a key, `algorithm=e3t`, sets the key too, so it wins over the file), merged in that
    order by OmegaConf and checked."""
    chosen = [(item, is_group_choice(item)) for item in overrides]
    # A group chosen more than once keeps its last choice, as a key set more than once keeps its last value.
    choices = list({item.partition("=")[0].strip(): item for item, choice in chosen if choice}.values())
    keys = [item for item, choice in chosen if not choice or is_config_key(schema, item.partition("=")[0].strip())]
    layers = [(sectioned(base or {}, schema), "the saved run config")]
    if path is not None or choices:
        layers.append((sectioned(compose(Path(path) if path is not None else None, choices, schema), schema),
                       str(path) if path is not None else "the command line"))
    layers.append((parse_overrides(keys, schema), "the command line"))
    merged = OmegaConf.structured(structured_schema(schema))
    for values, source in layers:
        merged = merge_layer(schema, merged, values, source)
    return build_config(schema, OmegaConf.to_container(merged)).check()


def save_config(config: TrainConfig | EvalConfig, path: str | Path) -> None:
    Path(path).write_text(yaml.safe_dump(dataclasses.asdict(config), sort_keys=False))
