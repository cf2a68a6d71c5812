"""What a command's config is: one dataclass per command, every field with its one-line meaning, and the checks.

Two schemas: `TrainConfig` (a training run, `train`) and `EvalConfig` (an evaluation of trained teams,
`evaluation`). A training config has three sections (`sections`): `runtime` (`RuntimeConfig`: how the run uses the
machine, not part of what the run is; an evaluation's `runtime` is its device and threads, `DeviceConfig`),
`distill` (`DistillConfig`: the planner-guided start) and `algorithm_config` (the algorithm's own settings, which its
class reads into a dataclass of its own with `settings_from`, `trainers.algorithms.Algorithm.Settings`); their keys
are `runtime.threads`, `distill.rounds`, `algorithm_config.partner_epsilon`. Values become a checked dataclass layer
by layer (`schema`: `merge_layer`, then `build_config`), and `check()` refuses values no run can use before any work
starts, with one line (a `ConfigError`) that says what to change. How the layers come from files and the command
line: `compose`.
"""

from trainers.config.evaluation import EVAL_COLLECTORS, EvalConfig
from trainers.config.schema import (
    MAX_SEED,
    ConfigError,
    build_config,
    check_cpp_compiler,
    check_device,
    config_keys,
    is_config_key,
    merge_layer,
    option,
    settings_from,
    structured_schema,
    type_hints,
    type_name,
    unknown_key,
)
from trainers.config.sections import (
    COLLECTORS,
    TEACHER_MIXES,
    DeviceConfig,
    DistillConfig,
    PPOConfig,
    RuntimeConfig,
    sectioned_keys,
)
from trainers.config.train import GENERATED_LEVELS, LOGGERS, PLANNER_START, RESUMABLE, TrainConfig, learning_keys

__all__ = [
    "COLLECTORS", "EVAL_COLLECTORS", "GENERATED_LEVELS", "LOGGERS", "MAX_SEED", "PLANNER_START", "RESUMABLE",
    "TEACHER_MIXES", "ConfigError", "DeviceConfig", "DistillConfig", "EvalConfig", "PPOConfig", "RuntimeConfig",
    "TrainConfig", "build_config", "check_cpp_compiler", "check_device", "config_keys", "is_config_key",
    "learning_keys", "merge_layer", "option", "sectioned_keys", "settings_from", "structured_schema", "type_hints",
    "type_name", "unknown_key",
]
