"""How a run stops and starts again: the signals that stop it after a checkpoint, the errors that end it, a fresh
start's clean logs, and a resumed run's state and logs put back as they were at its latest checkpoint."""

from __future__ import annotations

import shutil
import signal
from pathlib import Path

from tqdm import tqdm

from trainers.checkpoint import check_identity, load_checkpoint
from trainers.config import RESUMABLE, ConfigError, TrainConfig
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


def restore(team: TrainingTeam) -> dict:
    """Loads `team`'s latest checkpoint into its parts (networks, optimizer, its kitchens) and its algorithm, and
    sets its counters; returns the checkpoint (for its RNG states)."""
    state = load_checkpoint(team.checkpoint_path, map_location=team.config.runtime.device)
    check_identity(state, team.identity)
    check_same_learning(team.run, team.config, state["config"])
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

