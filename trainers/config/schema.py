"""How a config's values become a checked dataclass: `option` (a field with its one-line meaning), the checks
every schema shares (types, bounds, seed, name, device, a C++ compiler for compiled runs), and the layer machinery:
OmegaConf merges and converts the values over structured configs built from the dataclasses (`structured_schema`,
`merge_layer`), refuses unknown keys and ill-typed values with the valid keys (`unknown_key`), and `build_config`
makes the dataclass. The schemas themselves: `trainers.config.train`, `sections`, `evaluation`."""

from __future__ import annotations

import copy
import dataclasses
import difflib
import functools
import math
import shutil
import types
import typing
from pathlib import Path

import jax
import torch
from omegaconf import DictConfig, OmegaConf
from omegaconf.errors import OmegaConfBaseException


class ConfigError(ValueError):
    """A config file or override that cannot be used; the message says what to change."""


# torch takes 64-bit seeds, but JAX (32-bit by default) keeps only a seed's low 32 bits: 2**32 + 5 would replay 5.
MAX_SEED = 2**32 - 1


def option(default, help: str, group: str | None = None):
    """A config field with its one-line meaning (`help`, listed by `config_help`); a list or dict default is copied
    for every instance. `group` starts a new group of keys in `config_help`."""
    metadata = {"help": help} if group is None else {"help": help, "group": group}
    if isinstance(default, list | dict) or dataclasses.is_dataclass(default):
        return dataclasses.field(default_factory=lambda: copy.deepcopy(default), metadata=metadata)
    return dataclasses.field(default=default, metadata=metadata)



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


def check_types(config, prefix: str = "") -> None:
    """Refuses a field of the dataclass `config` whose value does not fit its type (a config built in Python skips
    `_merge`), its sections' fields too; a field is named with `prefix` (its section's, e.g. "runtime.")."""
    hints = type_hints(type(config))
    for field in dataclasses.fields(config):
        value, expected = getattr(config, field.name), hints[field.name]
        if dataclasses.is_dataclass(expected) and isinstance(value, expected):
            check_types(value, f"{prefix}{field.name}.")
        elif not _matches(value, expected):
            raise ConfigError(f"{prefix}{field.name} must be {type_name(expected)}, got {value!r}")
        elif expected is float and not math.isfinite(value):  # YAML reads .inf and .nan, float() reads "nan"
            raise ConfigError(f"{prefix}{field.name} must be a finite number, got {value}")


def at_least(config, names: list[str], low: int, prefix: str = "") -> None:
    """Refuses a field of `names` below `low`, named with `prefix` (its section's, e.g. "runtime.")."""
    for name in names:
        if not getattr(config, name) >= low:
            raise ConfigError(f"{prefix}{name} must be at least {low}, got {getattr(config, name)}")


def check_seed(seed: int) -> None:
    if not 0 <= seed <= MAX_SEED:
        raise ConfigError(
            f"seed must be an integer in [0, {MAX_SEED}] (JAX keeps only the low 32 bits of a seed), got {seed}"
        )


def check_name(name: str) -> None:
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
    moved = [known for known in keys if known.endswith(f".{key}") or known == key.replace("_", ".", 1)]
    short: dict[str, str] = {}  # a section's key by its own name (`lr` -> `ppo.lr`), the first section's
    for known in keys:
        short.setdefault(known.rpartition(".")[2], known)
    hint = (moved or difflib.get_close_matches(key, keys, n=1)
            or [short[name] for name in difflib.get_close_matches(key, list(short), n=1)])
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
    check_types(settings, prefix)
    return settings
