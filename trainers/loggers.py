"""A run's loggers: TorchRL's, by the names in `config.loggers` (tensorboard, csv, wandb, mlflow, trackio), under the
run directory, and the config as TensorBoard's hyperparameters."""

from __future__ import annotations

from pathlib import Path

from torchrl.record.loggers import Logger, get_logger

from torch_kitchen.torchrl_internals import PurgingTensorboardLogger
from trainers.config import TrainConfig


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


# ------------------------------------------------------------------------------------------- each update
