"""kitchen-sweep: a grid of training runs through a Hydra launcher, on this machine or on a SLURM cluster.

    kitchen-sweep CONFIG seed=0,1,2 architecture=mlp,gnn [hydra/launcher=joblib|submitit_local|submitit_slurm]
                  [hydra.launcher.partition=gpu hydra.launcher.timeout_min=720 hydra.launcher.gpus_per_node=1 ...]

Every config key takes Hydra's sweep grammar (`a,b,c`, `range(0,6)`); the grid is the product of the keys given
several values, and each point of it is the run `kitchen-train CONFIG key=value ...` would train. Its directory is
`<run_dir>/<name>/seed<k>` when only seeds vary and `<run_dir>/<name>/<key=value,...>/seed<k>` when other keys vary
too, so `kitchen-eval`'s `runs/<name>/seed*` globs keep working. `teams=K` makes every job train seeds seed ..
seed+K-1 together in one process, the paper's six teams of a condition in one job.

The config group `regime` (configs/regime/, as in `kitchen-train CONFIG regime=...` and the shipped configs'
`defaults:`) sets the paper's regimes: `ik` (levels=infinite hidden=256 share_params=true) and `sk_<layout>` (one
expanded layout, hidden=128, share_params=false). So the paper's grid is one sweep, its runs named as the shipped
configs name them:

    kitchen-sweep configs/ippo/mlp_ik.yaml regime=ik,sk_cramped_room,sk_coord_ring architecture=mlp,gnn \
        'name=ippo_${architecture}_${hydra:runtime.choices.regime}' seed=0 teams=6

A name that interpolates what varies names the runs by itself; otherwise the varying keys become a folder.

Launchers (`hydra/launcher=`, the sweep extra installs them): `basic` (default: the runs one after another in this
process), `joblib` (processes on this machine), `submitit_slurm` (one SLURM job per run, as an array; partition,
time, GPUs, array parallelism as `hydra.launcher.*`), `submitit_local` (the same code path without a scheduler).

A job resumes its run from the latest checkpoint where one exists and returns at once where the run is done: a
SLURM job that is preempted or times out is requeued by submitit's checkpoint hook and continues where its last
checkpoint left it, its logs cut back to that checkpoint (no row twice); a sweep run again completes what is
missing. Hydra's own files (each job's composed config and log, submitit's folders) go to
`<run_dir>/<name>/.sweeps/<date>_<time>/`.

Every key and every value is checked before a job starts, with `kitchen-train`'s messages.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Sequence
from contextlib import contextmanager

from trainers.algorithms import algorithm_settings, check_algorithm
from trainers.config import (
    ConfigError,
    TrainConfig,
    config_help,
    group_choices,
    group_values,
    is_config_key,
    load_config,
    unknown_key,
)
from trainers.plugins import PluginError, add_plugin_option, import_plugins
from trainers.train_command import train_or_resume
from trainers.training_run import team_configs

PRIMARY = "kitchen_sweep"  # the name of the sweep's base config in Hydra's ConfigStore
REGIME = "regime"  # the config group of the paper's regimes


def regimes() -> dict[str, dict]:
    """The paper's training regimes, the choices of the `regime` config group (configs/regime/): "ik" (Infinite
    Kitchen: a generated level every episode, one network shared by both agents, hidden 256) and "sk_<layout>"
    (Single Kitchen on one expanded layout, one network per agent, hidden 128), each with the values it sets."""
    return {choice: group_values(REGIME, choice) for choice in group_choices(REGIME)}


def run_point(cfg) -> list[str]:
    """One point of the grid (a Hydra task): trains, resumes or skips its run; returns its run directories."""
    import_plugins()  # a job in a process of its own imports the sweep's plugins too
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf

    logging.getLogger("jax").setLevel(logging.WARNING)  # Hydra logs at INFO; JAX's backend search is noise there
    config = load_config(base=OmegaConf.to_container(cfg, resolve=True))
    varied = HydraConfig.get().job.override_dirname  # the keys that vary in this sweep, but the seed
    if varied and not names_itself(cfg):
        config = load_config(base={**config.to_dict(), "name": f"{config.name}/{varied}"})
    return [str(run) for run in train_or_resume(team_configs(config))]


def names_itself(cfg) -> bool:
    """Whether the run name interpolates what varies: name=ippo_${architecture}_${hydra:runtime.choices.regime}."""
    from omegaconf import OmegaConf

    return "${" in str(OmegaConf.to_container(cfg, resolve=False)["name"])


def split_overrides(overrides: Sequence[str]) -> tuple[list[str], list[str]]:
    """(overrides of config keys, Hydra's own: `hydra.*`, `hydra/launcher=...`, `--flags`)."""
    ours, hydras = [], []
    for item in overrides:
        key = item.partition("=")[0].lstrip("+~")
        (hydras if key.startswith(("hydra", "-")) else ours).append(item)
    return ours, hydras


def grid_values(config_path: str, overrides: Sequence[str]) -> dict[str, list[str]]:
    """key -> its values in the grid, each value checked as `kitchen-train CONFIG key=value` would check it."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    values = {}
    for item in overrides:
        try:
            (override,) = OverridesParser.create().parse_overrides([item])
        except OverrideParseException as error:
            raise ConfigError(f"cannot read the override {item!r}: {error}") from None
        key = override.key_or_group
        if not is_config_key(TrainConfig, key) and key != REGIME:
            raise unknown_key(TrainConfig, key, "the command line")
        if override.is_sweep_override():
            values[key] = list(override.sweep_string_iterator())
        else:
            values[key] = [item.partition("=")[2]]  # as written: Hydra's string form escapes interpolations
    for choice in values.get(REGIME, []):
        if choice not in regimes():
            raise ConfigError(f"unknown regime {choice!r}; the regimes: {', '.join(regimes())}")
    first = {key: options[0] for key, options in values.items()}
    points = [first, *({**first, key: value} for key, options in values.items() for value in options[1:])]
    for point in points:  # the first point, and each other value beside the first value of every other key
        check_algorithm(load_config(config_path, point_overrides(point)))
    return values


def point_overrides(point: dict[str, str]) -> list[str]:
    """The key=value overrides of one point of the grid, in Hydra's order: the regime's values, then the keys."""
    regime = regimes()[point[REGIME]] if REGIME in point else {}
    return [*(f"{key}={value}" for key, value in regime.items()),
            *(f"{key}={value}" for key, value in point.items() if key != REGIME)]


@contextmanager
def command_line(arguments: list[str]):
    """sys.argv as Hydra's entry point reads it, for the time of the sweep."""
    saved = sys.argv
    sys.argv = ["kitchen-sweep", *arguments]
    try:
        yield
    finally:
        sys.argv = saved


def sweep(config_path: str, overrides: Sequence[str]) -> None:
    """Runs the grid of `overrides` over the config file `config_path` through Hydra's multirun."""
    import hydra
    from hydra.core.config_store import ConfigStore

    ours, hydras = split_overrides(overrides)
    base = load_config(config_path)
    grid = grid_values(config_path, ours)
    fixed = {key: values[0] for key, values in grid.items() if len(values) == 1}
    single = load_config(config_path, point_overrides(fixed))
    swept_name = len(grid.get("name", [])) > 1 or "${" in single.name
    named = "." if swept_name else single.name  # Hydra's files beside the runs when the name varies
    not_named = sorted({"seed", *fixed})  # run directories name the keys that vary, but the seed
    store = ConfigStore.instance()
    for choice, values in regimes().items():
        store.store(group=REGIME, name=choice, node=values, package="_global_")  # its keys at the top
    store.store(name=PRIMARY, node={"defaults": ["_self_", {REGIME: None}], **base.to_dict()})
    settings = [
        f"hydra.sweep.dir={single.run_dir}/{named}/.sweeps/${{now:%Y-%m-%d_%H-%M-%S}}",
        f"hydra.job.config.override_dirname.exclude_keys=[{','.join(not_named)}]",
        "hydra.job.chdir=false",
    ]
    with command_line(["--multirun", *settings, *hydras, *ours]):
        hydra.main(version_base="1.3", config_path=None, config_name=PRIMARY)(run_point)()


def main(argv: Sequence[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="kitchen-sweep", description=__doc__,
                                     epilog=config_help(TrainConfig, algorithm_settings()),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", help="a YAML config (configs/...)")
    parser.add_argument("overrides", nargs="*", help="key=a,b,c sweeps and key=value overrides; hydra.* settings")
    add_plugin_option(parser)
    args = parser.parse_args(argv)
    try:
        import hydra  # noqa: F401
    except ImportError:
        print("kitchen-sweep: error: sweeps need the sweep extra: pip install .[sweep]", file=sys.stderr)
        return 2
    try:
        import_plugins(args.plugins)  # and again in every job (run_point), from the environment
        sweep(args.config, args.overrides)
    except (ConfigError, PluginError) as error:
        print(f"kitchen-sweep: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
