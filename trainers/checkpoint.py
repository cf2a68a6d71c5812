"""Checkpoints: one file per save holding everything a run needs to continue exactly where it stopped.

Contents: the resolved config, the model's identity (architecture, observation shape, width, parameter
sharing), actor and critic weights, the optimizer, the update and env-step counters, the RNG states, and the
environment's kitchens. Files are written to a temporary name and renamed, so a run killed while saving keeps
its previous checkpoint intact.

A checkpoint is data, not code: it holds only tensors and plain Python values, `save_checkpoint` refuses
anything else, and `load_checkpoint` reads with `torch.load(weights_only=True)`, so a crafted file is refused
before anything in it runs.
"""

from __future__ import annotations

import os
import pickle
import random
import re
import warnings
from collections import OrderedDict
from pathlib import Path

import numpy as np
import torch

FORMAT = 2  # 1: pickles with numpy arrays and JAX states inside, which only an unrestricted unpickler reads
LATEST = "latest.pt"

# What `torch.load(weights_only=True)` rebuilds without running code. Exact types: a subclass (a numpy float,
# an enum, a named tuple) is pickled under its own name and refused at load.
_PLAIN = (str, int, float, bool, type(None))
_LEAVES = (*_PLAIN, torch.Tensor, torch.nn.Parameter, torch.Size, torch.dtype, torch.device)
_OLDER = "written by an older version of Infinite Kitchen (format 1); retrain, or load it with that version"


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used here; the message says why and what to do instead."""


def check_plain(value, path: str = "payload") -> None:
    """Raises a `TypeError` naming the first entry of `value` that is not a tensor or a plain Python value."""
    kind = type(value)
    if kind in (dict, OrderedDict):
        for key, item in value.items():
            if type(key) not in _PLAIN:
                raise TypeError(f"cannot checkpoint {path}: its key {key!r} is a {_name(type(key))}")
            check_plain(item, f"{path}[{key!r}]")
        if kind is OrderedDict and vars(value):  # state dicts carry their `_metadata` as an attribute
            check_plain(vars(value), f"{path}.__dict__")
    elif kind in (list, tuple):
        for index, item in enumerate(value):
            check_plain(item, f"{path}[{index}]")
    elif kind not in _LEAVES:
        raise TypeError(
            f"cannot checkpoint {path}: a {_name(kind)}; checkpoints hold only tensors and plain Python values "
            "(dict, list, tuple, str, int, float, bool, None): convert it, e.g. with torch.as_tensor"
        )


def _name(kind: type) -> str:
    return kind.__qualname__ if kind.__module__ == "builtins" else f"{kind.__module__}.{kind.__qualname__}"


def save_checkpoint(path: str | Path, payload: dict) -> Path:
    """Writes `payload` (tensors and plain values only, else a `TypeError`) atomically to `path`."""
    payload = {"format": FORMAT, **payload}
    check_plain(payload)  # before writing: a checkpoint that could not be loaded must never replace a good one
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_name(path.name + ".partial")
    torch.save(payload, partial)
    os.replace(partial, path)
    return path


def checkpoint_file(path: str | Path) -> Path:
    """The checkpoint file `path` names: itself, or a run directory's latest checkpoint."""
    path = Path(path)
    return path / "checkpoints" / LATEST if path.is_dir() else path


def load_checkpoint(path: str | Path, map_location: str | torch.device = "cpu") -> dict:
    """The payload of a checkpoint file (a file, or a run directory whose latest checkpoint to take).

    Anything that is not a checkpoint of this version is refused with a `CheckpointError`, without running it.
    """
    path = checkpoint_file(path)
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}: give a checkpoint file or a run directory that has one")
    with open(path, "rb") as handle:
        head = handle.read(4)
    if not head.startswith((b"PK\x03\x04", b"\x80")):  # neither torch.save's zip nor a pickle, whole or cut short
        raise CheckpointError(f"{path} is not a checkpoint: not a file torch.save writes (a run keeps its own in "
                              "RUN/checkpoints/latest.pt)")
    try:
        with warnings.catch_warnings():  # a bare pickle of another protocol: refused below, no need to warn
            warnings.filterwarnings("ignore", message="Detected pickle protocol")
            payload = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as error:
        raise _refusal(path, str(error)) from None
    except Exception as error:  # a damaged file fails in many ways (zip, storage, EOF...); none of it ran code
        raise _unreadable(path, error) from None
    if not isinstance(payload, dict) or "format" not in payload or "model" not in payload:
        raise CheckpointError(f"{path} is not an Infinite Kitchen checkpoint (no format and model entries)")
    found = payload["format"]
    if type(found) is int and found == 1:
        raise CheckpointError(f"{path} was {_OLDER}")
    if type(found) is not int or found != FORMAT:
        raise CheckpointError(
            f"{path} is a checkpoint of format {found!r}, this version reads format {FORMAT}: load it with the "
            "version that wrote it"
        )
    payload["path"] = str(path)
    return payload


def _refusal(path: Path, message: str) -> CheckpointError:
    """Why torch's weights-only unpickler stopped: objects that run code, a format-1 file, or damage."""
    try:  # a static scan of the pickle's imports: reads opcodes, runs nothing
        names = sorted(torch.serialization.get_unsafe_globals_in_checkpoint(path))
    except Exception:  # not torch's zip format (e.g. a bare pickle): the unpickler's message names what it met
        names = re.findall(r"GLOBAL (\S+) (?:was not an allowed|whose module)", message)
    if names and all(name.split(".")[0] in ("numpy", "jax_env") for name in names):
        return CheckpointError(f"{path} holds numpy arrays: it was {_OLDER}")
    if names or "Unsupported operand" not in message:
        listed = f" ({', '.join(names[:3])}{', ...' if len(names) > 3 else ''})" if names else ""
        return CheckpointError(
            f"{path} holds objects other than tensors and plain values{listed}: not an Infinite Kitchen "
            "checkpoint (refused without running it)"
        )
    return _unreadable(path, pickle.UnpicklingError(message[message.index("Unsupported operand") :]))


def _unreadable(path: Path, error: Exception) -> CheckpointError:
    line = next((line.strip() for line in str(error).splitlines() if line.strip()), "")
    reason = f"{type(error).__name__}: {line[:200]}" if line else type(error).__name__
    return CheckpointError(
        f"{path} is not a readable checkpoint ({reason}); it may be truncated or corrupt: use an earlier "
        "checkpoint of the run or retrain"
    )


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


# ---------------------------------------------------------------------------------------------------- RNG
def capture_rng_states() -> dict:
    """The states of Python's `random`, NumPy's global RNG, torch's CPU RNG and every CUDA device's (an empty
    list where CUDA is not in use), as tensors and plain values for a checkpoint; `restore_rng_states` sets them back.

    The env's JAX key and E3T's partner seats (their torch generator included) are not here: they travel in
    `env.state_dict()` and in the algorithm's state dict (`PartnerSeats.state_dict()`).
    """
    version, internal, gauss_next = random.getstate()
    bit_generator, keys, position, has_gauss, cached_gaussian = np.random.get_state(legacy=True)
    return {
        "python": {"version": version, "internal": list(internal), "gauss_next": gauss_next},
        "numpy": {
            "bit_generator": str(bit_generator),
            "keys": torch.from_numpy(keys.astype(np.int64)),  # uint32, which torch supports only in part
            "position": int(position),
            "has_gauss": int(has_gauss),
            "cached_gaussian": float(cached_gaussian),
        },
        "torch": torch.get_rng_state(),
        # Only where CUDA is in use: asking an idle GPU machine for its states would start CUDA on every device.
        "torch_cuda": list(torch.cuda.get_rng_state_all()) if torch.cuda.is_initialized() else [],
    }


def restore_rng_states(states: dict) -> None:
    """Sets the RNGs to a `capture_rng_states` result. CUDA states go to as many devices as this machine has
    (none without CUDA), so a run resumes on a machine with fewer GPUs."""
    python = states["python"]
    random.setstate((python["version"], tuple(python["internal"]), python["gauss_next"]))
    numpy = states["numpy"]
    keys = numpy["keys"].cpu().numpy().astype(np.uint32)
    np.random.set_state((numpy["bit_generator"], keys, numpy["position"], numpy["has_gauss"], numpy["cached_gaussian"]))
    # States are CPU byte tensors whatever device the checkpoint was loaded onto.
    torch.set_rng_state(states["torch"].cpu())
    cuda = states["torch_cuda"]
    if cuda and torch.cuda.is_available():
        torch.cuda.set_rng_state_all([state.cpu() for state in cuda[: torch.cuda.device_count()]])
