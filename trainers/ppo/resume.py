"""How a run starts, stops and starts again: a fresh start's clean logs and its `init_from` weights, a resumed run's
state, random streams and logs put back as they were at its latest checkpoint, its loggers (TorchRL's, by the names
in `config.loggers`), the signals that stop a run after its next checkpoint (`StopRequest`), and the errors that end
it."""

from __future__ import annotations

import shutil
import signal
from collections.abc import Sequence
from pathlib import Path

from torchrl.record.loggers import Logger, get_logger
from tqdm import tqdm

from torch_kitchen.partners.conventions import fingerprints
from torch_kitchen.torchrl_internals import PurgingTensorboardLogger
from trainers.algorithms import ALGORITHMS
from trainers.checkpoint import check_identity, load_checkpoint, restore_rng_states
from trainers.config import RESUMABLE, ConfigError, TrainConfig
from trainers.config.compose import save_config
from trainers.ppo.team import TrainingTeam


class RunStopped(Exception):
    """A run stopped by a signal (Ctrl-C: SIGINT, or SIGTERM); `exit_code` is 128 + the signal's number."""

    def __init__(self, signum: int, message: str):
        super().__init__(message)
        self.exit_code = 128 + signum

    def __reduce__(self):  # raised again in the process that waits on a condition trained in another
        return type(self), (self.exit_code - 128, str(self))


class TrainingDiverged(RuntimeError):
    """A loss became NaN or infinite; the last good state is in the run's latest checkpoint."""


def start_fresh(run: Path) -> None:
    """A run directory without a checkpoint (a run killed before its first one) starts clean: its logs are
    removed, so the new run's logs are not appended to them."""
    for logs in ("csv", "tensorboard"):
        shutil.rmtree(run / logs, ignore_errors=True)


def check_same_learning(run: Path, config: TrainConfig, trained: dict, resumable: tuple[str, ...] = RESUMABLE) -> None:
    """Refuses, in one line, to resume `run` (trained with the config `trained`) with a `config` that would change
    what it learns: only `resumable` and runtime.* may change."""
    if changed := config.changes_to_learning(trained, resumable):
        was = ", ".join(f"{key}={value!r}" for key, (value, _) in changed.items())
        asked = ", ".join(f"{key}={value!r}" for key, (_, value) in changed.items())
        raise ConfigError(f"{run} was trained with {was}, not {asked}: a resume keeps what the run learns "
                          f"(only {', '.join(resumable)} and runtime.* may change); train these settings under "
                          "another name= or run_dir=")


def load_to_resume(run: Path, checkpoint: Path, config: TrainConfig, identity: dict,
                   resumable: tuple[str, ...] = RESUMABLE) -> dict:
    """The `checkpoint` of `run`, to go on with `config`: refused where its model is not `identity` or where `config`
    would change what it learns (`check_same_learning`)."""
    state = load_checkpoint(checkpoint, map_location=config.runtime.device)
    check_identity(state, identity)
    check_same_learning(run, config, state["config"], resumable)
    return state


def check_same_partners(run: Path, config: TrainConfig, met: dict[str, str] | None) -> None:
    """Refuses, in one line, to resume `run` (whose checkpoint recorded the conventions it `met`, by fingerprint)
    with a `config` whose algorithm meets a scripted convention not among them: the zoo file it names was redrawn
    since, or names others, and a resume keeps a run's partners. A checkpoint that recorded none is not checked."""
    now = fingerprints(ALGORITHMS[config.algorithm].met_conventions(config))
    if met is not None and (new := sorted(name for fingerprint, name in now.items() if fingerprint not in met)):
        raise ConfigError(f"{run} was not trained beside {', '.join(new)} as {config.zoo} holds them now (a zoo "
                          "redrawn since?): a resume keeps a run's partners; train under another name= or run_dir=")


def restore(team: TrainingTeam) -> dict:
    """Loads `team`'s latest checkpoint into its parts (networks, optimizer, its kitchens) and its algorithm, and
    sets its counters; returns the checkpoint (for its RNG states)."""
    state = load_to_resume(team.run, team.checkpoint_path, team.config, team.identity)
    check_same_partners(team.run, team.config, state.get("met"))
    for name, part in team.parts.items():
        part.load_state_dict(state[name])
    team.algorithm.load_state_dict(state["algorithm"])
    team.update, team.env_steps = state["update"], state["env_steps"]
    team.met.update(state.get("met", {}))
    return state


def drop_csv_rows_after(csv_dir: Path, env_steps: int) -> None:
    """Removes the CSV rows a killed run logged after its last checkpoint, so a resumed run does not repeat them."""
    for path in csv_dir.rglob("*.csv"):
        rows = [line for line in path.read_text().splitlines() if line and int(float(line.split(",")[0])) <= env_steps]
        path.write_text("".join(row + "\n" for row in rows))


class StopRequest:
    """First Ctrl-C (or SIGTERM): finish the current update, checkpoint, stop. Second one: stop at once."""

    def __init__(self):
        self.signum: int | None = None
        self._previous = {}

    def __enter__(self):
        for signum in (signal.SIGINT, signal.SIGTERM):
            try:
                self._previous[signum] = signal.signal(signum, self._handle)
            except ValueError:  # not the main thread: leave signals alone
                pass
        return self

    def _handle(self, signum, frame):
        if self.signum is not None:
            raise RunStopped(signum, f"stopped by {signal.Signals(signum).name} before the update ended; "
                                     "its latest checkpoint is the last one written")
        self.signum = signum
        tqdm.write("stopping after this update (checkpoint first); press Ctrl-C again to stop at once")

    def __exit__(self, *exc):
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)


def start_from(team: TrainingTeam) -> None:
    """Loads into `team` the actor's and critic's weights that its `init_from` names (nothing to load from scratch):
    a run's latest checkpoint, or its planner-guided start. CheckpointError if that model is not the team's."""
    start = team.config.init_path(team.run)
    if start is None:
        return
    state = load_checkpoint(start, map_location=team.config.runtime.device)
    check_identity(state, team.identity)
    team.parts["actor"].load_state_dict(state["actor"])
    team.parts["critic"].load_state_dict(state["critic"])
    team.met.update(state.get("met", {}))  # what the start met, the team met


def resume_or_start(teams: Sequence[TrainingTeam], resume: bool) -> list[dict | None]:
    """`resume`: every team restored from its latest checkpoint (all at one update), the CSV rows logged after it
    dropped; else every team's old logs removed and its `init_from` weights loaded. Returns the checkpoints (their
    RNG states are put back once the collector is built), None for a fresh start."""
    if not resume:
        for team in teams:
            start_fresh(team.run)
            start_from(team)
        return [None] * len(teams)
    saved = [restore(team) for team in teams]
    if len({team.update for team in teams}) > 1:
        at = ", ".join(f"{team.run} at update {team.update}" for team in teams)
        raise ConfigError(f"teams resumed together must be at the same update ({at}): resume them one by one")
    for team in teams:
        drop_csv_rows_after(team.run / "csv", team.env_steps)
    return saved


def already_trained(teams: list[TrainingTeam], remaining: int) -> bool:
    """Saves every team's config into its run directory; says so and returns True where no update remains."""
    for team in teams:
        team.run.mkdir(parents=True, exist_ok=True)
        save_config(team.config, team.run / "config.yaml")
        if remaining <= 0:
            print(f"{team.run}: already trained for {team.update} updates ({team.env_steps:,} steps); raise "
                  "total_steps to go on")
    return remaining <= 0


def restore_streams(teams: list[TrainingTeam], saved: list[dict | None]) -> None:
    """Each resumed team's random streams as its checkpoint left them."""
    for team, state in zip(teams, saved):
        if state is not None:
            with team.stream.active():
                restore_rng_states(state["rng"])


def make_loggers(config: TrainConfig, run: Path, purge_step: int | None) -> list[Logger]:
    """TorchRL loggers named by `config.loggers`, writing under `run/<name>`. TensorBoard drops the events a killed
    run wrote at steps >= `purge_step` (a resume); other backends (wandb, mlflow, ...) come from `get_logger`."""
    loggers = []
    for name in config.loggers:
        if name == "tensorboard":
            loggers.append(PurgingTensorboardLogger("tensorboard", str(run), purge_step=purge_step))
        else:  # the CSV files go to run/csv; a tracking service names the experiment after the run
            experiment = "csv" if name == "csv" else f"{config.name}-seed{config.seed}"
            loggers.append(get_logger(name, logger_name=str(run), experiment_name=experiment))
    return loggers


def hyperparameters(config: TrainConfig) -> dict[str, int | float | str | bool]:
    """The config as TensorBoard's hparams accept it (lists as text)."""
    return {key: value if isinstance(value, int | float | str | bool) else str(value)
            for key, value in config.to_dict().items()}


def close_logs(teams: list[TrainingTeam]) -> None:
    """Every team's loggers closed (their last rows written)."""
    for team in teams:
        for logger in team.loggers:
            logger.close()


def open_logs(teams: list[TrainingTeam], resume: bool) -> None:
    """Every team's loggers (a resumed run's logs cut at its checkpoint's step), with its hyperparameters once."""
    for team in teams:
        hparams = hyperparameters(team.config)
        team.loggers = make_loggers(team.config, team.run, purge_step=team.env_steps + 1 if resume else None)
        if not resume:
            for logger in team.loggers:
                logger.log_hparams(hparams)
