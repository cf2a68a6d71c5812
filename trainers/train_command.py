"""`kitchen-train`: the command line of the PPO trainer (`trainers.ppo.loop`).

    kitchen-train configs/ippo/mlp_ik.yaml seed=3 total_steps=1e6
    kitchen-train --resume runs/ippo_mlp_ik/seed3 total_steps=2e6
    kitchen-train configs/ippo/mlp_ik.yaml --import my_models architecture=my_net

A config file and key=value overrides (`teams=K` trains seeds seed .. seed + K - 1 together), or saved runs to
continue. Every error is one line (exit 2; a diverged loss exits 1); a signal stops the run after a checkpoint
(exit 128 + its number) and the line printed says how to continue it.
"""

from __future__ import annotations

import argparse
import shutil
import sys
import time
from collections.abc import Sequence
from pathlib import Path

from trainers.algorithms import algorithm_settings
from trainers.checkpoint import LATEST, CheckpointError
from trainers.config import ConfigError, TrainConfig
from trainers.config.compose import load_config, train_config_parser
from trainers.plugins import PluginError, add_plugin_option, import_plugins
from trainers.ppo.loop import train_teams
from trainers.ppo.resume import RunStopped, TrainingDiverged
from trainers.ppo.team import team_configs


def train_or_resume(configs: Sequence[TrainConfig]) -> list[Path]:
    """Trains the teams of `configs` together, or resumes them where every one has a checkpoint (teams already
    trained return at once), so running the same command again continues it. Teams of which only some have a
    checkpoint start over together: teams trained in one batch resume from one update."""
    if latest_checkpoints(configs) is not None:
        return train_teams(configs, resume=True)
    for config in configs:
        shutil.rmtree(config.run_path, ignore_errors=True)
    return train_teams(configs)


def latest_checkpoints(configs: Sequence[TrainConfig]) -> list[Path] | None:
    """Each team's latest checkpoint where every team has one (they resume together); None where some or all have
    none: teams trained in one batch resume from one update, so those start over together."""
    paths = [config.run_path / "checkpoints" / LATEST for config in configs]
    return paths if all(path.is_file() for path in paths) else None


def report_runs(config: TrainConfig, runs: Sequence[Path]) -> None:
    """Each trained run's self-play table, learning curve and GIF, in its folder, as `eval_episodes` asks (0:
    none): what `kitchen-train` and every job of `kitchen-sweep` end with."""
    if config.eval_episodes > 0:
        from trainers.evaluation import report_trained_team  # the evaluation's imports only where it runs

        for run in runs:
            report_trained_team(run)


def train_config_file(path: str, overrides: Sequence[str]) -> float:
    """`train_or_resume` of the teams a config file and its overrides name; returns the wall seconds it took. A
    process's task where conditions train side by side (`scripts/reproduce.py --jobs`)."""
    started = time.perf_counter()
    train_or_resume(team_configs(load_config(path, overrides)))
    return time.perf_counter() - started


def build_parser() -> argparse.ArgumentParser:
    parser = train_config_parser("kitchen-train", "Train a team with IPPO, E3T, anchored IPPO or a registered "
                                 "algorithm (TorchRL) on Single or Infinite Kitchen levels.", algorithm_settings())
    parser.add_argument("--resume", metavar="RUN_DIR", nargs="+",
                        help="continue the run in RUN_DIR from its latest checkpoint; several run directories (the "
                             "teams of a condition, e.g. runs/NAME/seed*) continue together in one batch; key=value "
                             "overrides may follow")
    parser.add_argument("--allow-unsolvable", action="store_true",
                        help="train on level files the solvability checker calls unsolvable (with a warning)")
    parser.add_argument("--eval-on-stop", action="store_true",
                        help="evaluate the team even when the run is stopped before total_steps")
    add_plugin_option(parser)
    return parser


def config_of(args: argparse.Namespace) -> tuple[list[TrainConfig], list[Path] | None]:
    """The teams a command line asks for: their configs (a YAML file and overrides, one per team, or saved runs'
    configs and overrides) and their run directories (None: the configs' own)."""
    if args.resume:
        # With --resume, key=value arguments are overrides (e.g. total_steps=...), the others run directories.
        arguments = [*args.resume, *([args.config] if args.config else []), *args.overrides]
        runs = [Path(item) for item in arguments if "=" not in item]
        overrides = [item for item in arguments if "=" in item]
        if any(item.startswith("runtime.teams=") for item in overrides):
            raise ConfigError("runtime.teams= starts new teams; resume several runs together by naming their "
                              "directories")
        configs = []
        for run in runs:
            saved = run / "config.yaml"
            if not saved.is_file():
                raise ConfigError(f"{run} is not a run directory (no config.yaml in it)")
            configs.append(load_config(saved, overrides))
        return configs, runs
    if args.config is None:
        raise ConfigError("give a config file (e.g. configs/ippo/mlp_ik.yaml) or --resume RUN_DIR")
    if "=" in args.config:
        raise ConfigError(f"the first argument must be a config file, got the override {args.config!r}")
    return team_configs(load_config(args.config, args.overrides)), None


def main(argv: Sequence[str] | None = None) -> int:
    args = build_parser().parse_intermixed_args(argv)  # overrides may follow --import MODULE
    stopped = None
    try:
        import_plugins(args.plugins)
        configs, runs = config_of(args)
        runs = runs or [config.run_path for config in configs]
        try:
            train_teams(configs, runs, resume=bool(args.resume), allow_unsolvable=args.allow_unsolvable)
        except RunStopped as error:
            stopped = error
            print(f"kitchen-train: {error}; continue with `kitchen-train --resume {' '.join(map(str, runs))}`",
                  file=sys.stderr)
        if stopped is None or args.eval_on_stop:
            report_runs(configs[0], runs)
    except (ConfigError, CheckpointError, ValueError, PluginError) as error:
        print(f"kitchen-train: error: {error}", file=sys.stderr)
        return 2
    except TrainingDiverged as error:
        print(f"kitchen-train: error: {error}", file=sys.stderr)
        return 1
    except RunStopped as error:  # a second signal, during the evaluation or while stopping
        print(f"kitchen-train: {error}", file=sys.stderr)
        return error.exit_code
    except KeyboardInterrupt:
        print("kitchen-train: stopped; resume from the last checkpoint with --resume", file=sys.stderr)
        return 130
    return stopped.exit_code if stopped is not None else 0


if __name__ == "__main__":
    sys.exit(main())
