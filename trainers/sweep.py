"""kitchen-sweep: a grid of training runs through a Hydra launcher, on this machine or on a SLURM cluster.

    kitchen-sweep CONFIG seed=0,1,2 architecture=mlp,gnn [hydra/launcher=joblib|submitit_local|submitit_slurm]
                  [hydra.launcher.partition=gpu hydra.launcher.timeout_min=720 hydra.launcher.gpus_per_node=1 ...]

Every config key takes Hydra's sweep grammar (`a,b,c`, `range(0,6)`); the grid is the product of the keys given
several values, and each point of it is the run `kitchen-train CONFIG key=value ...` would train. Its directory is
`<run_dir>/<name>/seed<k>` when only seeds vary and `<run_dir>/<name>/<key=value,...>/seed<k>` when other keys vary
too, so `kitchen-eval`'s `runs/<name>/seed*` globs keep working. `runtime.teams=K` makes every job train seeds
seed .. seed+K-1 together in one process, the paper's six teams of a condition in one job. Each job ends as
`kitchen-train` does: every run's self-play table (`eval.md`), learning curve and GIF in its folder, as its
`eval_episodes` and `gif` ask; the sweep ends by saying where the runs are.

The config groups (configs/algorithm, architecture, regime, runtime: `kitchen-train CONFIG regime=...` and the
shipped configs' `defaults:`) sweep as groups, composed by Hydra from the same files as `kitchen-train`'s: e.g.
the regimes `ik` (levels=infinite hidden=256 share_params=true) and `sk_<layout>` (one expanded layout, hidden=128,
share_params=false). So the paper's grid is one sweep, its runs named as the shipped configs name them:

    kitchen-sweep configs/ippo/mlp_ik.yaml regime=ik,sk_cramped_room,sk_coord_ring architecture=mlp,gnn \
        'name=ippo_${hydra:runtime.choices.architecture}_${hydra:runtime.choices.regime}' seed=0 runtime.teams=6

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
from pathlib import Path

from trainers.algorithms import algorithm_settings, check_algorithm
from trainers.config import ConfigError, TrainConfig, is_config_key, unknown_key
from trainers.config.compose import CONFIG_ROOT, GROUPS, config_help, group_choices, group_overrides, load_config
from trainers.plugins import PluginError, add_plugin_option, import_plugins
from trainers.ppo.team import team_configs
from trainers.train_command import report_runs, train_or_resume


def run_point(cfg) -> list[str]:
    """One point of the grid (a Hydra task): trains, resumes or skips its run; returns its run directories."""
    import_plugins()  # a job in a process of its own imports the sweep's plugins too
    from hydra.core.hydra_config import HydraConfig
    from omegaconf import OmegaConf

    logging.getLogger("jax").setLevel(logging.WARNING)  # Hydra logs at INFO; JAX's backend search is noise there
    config = load_config(base=OmegaConf.to_container(cfg, resolve=True))
    # the keys that vary in this sweep, but the seed, as key=value (without the `++` they are given with)
    varied = ",".join(item.lstrip("+") for item in HydraConfig.get().job.override_dirname.split(",") if item)
    if varied and not names_itself(cfg):
        config = load_config(base={**config.to_dict(), "name": f"{config.name}/{varied}"})
    runs = train_or_resume(team_configs(config))
    report_runs(config, runs)  # eval.md, the learning curve and the GIF, as kitchen-train writes them
    return [str(run) for run in runs]


def names_itself(cfg) -> bool:
    """Whether the run name interpolates what varies: name=ippo_${hydra:runtime.choices.regime}."""
    from omegaconf import OmegaConf

    return "${" in str(OmegaConf.to_container(cfg, resolve=False)["name"])


def split_overrides(overrides: Sequence[str]) -> tuple[list[str], list[str]]:
    """(overrides of config keys and groups, Hydra's own: `hydra.*`, `hydra/launcher=...`, `--flags`)."""
    ours, hydras = [], []
    for item in overrides:
        key = item.partition("=")[0].lstrip("+~")
        (hydras if key.startswith(("hydra", "-")) else ours).append(item)
    return ours, hydras


def grid_values(config_path: str, overrides: Sequence[str]) -> dict[str, list[str]]:
    """key or group -> its values in the grid, each checked as `kitchen-train CONFIG key=value` would check it."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.errors import OverrideParseException

    values = {}
    for item in overrides:
        try:
            (override,) = OverridesParser.create().parse_overrides([item])
        except OverrideParseException as error:
            raise ConfigError(f"cannot read the override {item!r}: {error}") from None
        key = override.key_or_group
        if not is_config_key(TrainConfig, key) and key not in GROUPS:
            raise unknown_key(TrainConfig, key, "the command line")
        if override.is_sweep_override():
            values[key] = list(override.sweep_string_iterator())
        else:
            values[key] = [item.partition("=")[2]]  # as written: Hydra's string form escapes interpolations
    first = {key: options[0] for key, options in values.items()}
    points = [first, *({**first, key: value} for key, options in values.items() for value in options[1:])]
    for point in points:  # the first point, and each other value beside the first value of every other key
        check_algorithm(load_config(config_path, point_overrides(point)))
    return values


def point_overrides(point: dict[str, str]) -> list[str]:
    """The key=value overrides of one point of the grid."""
    return [f"{key}={value}" for key, value in point.items()]


def as_hydra_overrides(config_path: str, grid: dict[str, list[str]]) -> list[str]:
    """The grid as Hydra's overrides over the file: a group whose values are all its choices sweeps as a group
    (`regime=ik,sk_coord_ring`, or `+regime=...` where the file chooses none), any other key as a value set whether
    or not the file names it (`++seed=0,1,2`)."""
    groups = [key for key, options in grid.items()
              if key in GROUPS and all(option in group_choices(key) for option in options)]
    swept = group_overrides(Path(config_path).resolve(), [f"{key}={','.join(grid[key])}" for key in groups])
    return [*swept, *(f"++{key}={','.join(options)}" for key, options in grid.items() if key not in groups)]


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
    """Runs the grid of `overrides` over the config file `config_path` through Hydra's multirun, which composes every
    point from the file as `kitchen-train` does (`trainers.config.compose.compose`)."""
    import hydra

    ours, hydras = split_overrides(overrides)
    grid = grid_values(config_path, ours)
    fixed = {key: values[0] for key, values in grid.items() if len(values) == 1}
    single = load_config(config_path, point_overrides(fixed))
    swept_name = len(grid.get("name", [])) > 1 or "${" in single.name
    named = "." if swept_name else single.name  # Hydra's files beside the runs when the name varies
    not_named = sorted({"seed", *fixed})  # run directories name the keys that vary, but the seed
    settings = [
        f"hydra.searchpath=[file://{CONFIG_ROOT}]",
        f"hydra.sweep.dir={single.run_dir}/{named}/.sweeps/${{now:%Y-%m-%d_%H-%M-%S}}",
        f"hydra.job.config.override_dirname.exclude_keys=[{','.join(not_named)}]",
        "hydra.job.chdir=false",
    ]
    path = Path(config_path).resolve()
    with command_line(["--multirun", *settings, *hydras, *as_hydra_overrides(config_path, grid)]):
        hydra.main(version_base="1.3", config_path=str(path.parent), config_name=path.stem)(run_point)()
    where = f"{single.run_dir}/" + ("<name>/" if swept_name else f"{single.name}/")
    print(f"kitchen-sweep: the runs are in {where} (each seed<k>, or <key=value,...>/seed<k> where other keys vary)")


def main(argv: Sequence[str] | None = None) -> int:
    import argparse

    parser = argparse.ArgumentParser(prog="kitchen-sweep", description=__doc__,
                                     epilog=config_help(TrainConfig, algorithm_settings()),
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("config", help="a YAML config (configs/...)")
    parser.add_argument("overrides", nargs="*", help="key=a,b,c sweeps and key=value overrides; hydra.* settings")
    add_plugin_option(parser)
    args = parser.parse_intermixed_args(argv)  # overrides may follow --import MODULE
    try:
        import_plugins(args.plugins)  # and again in every job (run_point), from the environment
        sweep(args.config, args.overrides)
    except (ConfigError, PluginError) as error:
        print(f"kitchen-sweep: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
