"""Checkpoints: one file per save holding everything a run needs to continue exactly where it stopped.

Contents: the resolved config, the model's identity (architecture, observation shape, width, parameter
sharing), actor and critic weights, the optimizer, the update and env-step counters, the RNG states, and the
environment's kitchens. Files are written to a temporary name and renamed, so a run killed while saving keeps
its previous checkpoint intact.
"""

from __future__ import annotations

import os
import pickle
import zipfile
from pathlib import Path

import torch

FORMAT = 1
LATEST = "latest.pt"


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used here; the message says why and what to do instead."""


def model_identity(architecture: str, obs_shape, hidden: int, share_params: bool) -> dict:
    """What must match for weights to load: compared before any tensor is touched."""
    return {
        "architecture": architecture,
        "obs_shape": list(obs_shape),
        "hidden": hidden,
        "share_params": share_params,
    }


def save_checkpoint(path: str | Path, payload: dict) -> Path:
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    torch.save({"format": FORMAT, **payload}, partial)
    os.replace(partial, path)
    return path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """The payload of a checkpoint file (a file, or a run directory whose latest checkpoint to take)."""
    path = Path(path)
    if path.is_dir():
        path = path / "checkpoints" / LATEST
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}: give a checkpoint file or a run directory that has one")
    try:
        payload = torch.load(path, map_location=map_location, weights_only=False)
    except (RuntimeError, EOFError, pickle.UnpicklingError, zipfile.BadZipFile, ValueError) as error:
        raise CheckpointError(
            f"{path} is not a readable checkpoint ({type(error).__name__}: {str(error).splitlines()[0][:200]}); "
            "it may be truncated or corrupt: use an earlier checkpoint of the run or retrain"
        ) from None
    if not isinstance(payload, dict) or payload.get("format") != FORMAT or "model" not in payload:
        raise CheckpointError(f"{path} is not an Infinite Kitchen checkpoint (format {FORMAT})")
    payload["path"] = str(path)
    return payload


def check_identity(payload: dict, expected: dict) -> None:
    """Raises a CheckpointError naming every field where the checkpoint's model differs from the expected one."""
    found = payload["model"]
    differences = [
        f"{key}: checkpoint {found.get(key)!r}, expected {value!r}"
        for key, value in expected.items()
        if found.get(key) != value
    ]
    if differences:
        raise CheckpointError(
            f"checkpoint {payload.get('path', '')} holds another model ({'; '.join(differences)}); "
            "load it with the config it was trained with (the run's config.yaml) or start a new run"
        )
