"""What a loop would cost on a GPU, counted on any machine: a torch function mode that records every tensor made by a
factory call without a device (on a GPU it lands on the CPU) and every read of a tensor's values by the host (on a
GPU each one waits for the device), each by the function of this project's code that led to it.

    with DeviceAudit() as audit:
        train(config)
    print(audit.report())

A loop's count at two lengths tells a per-step host read from a one-off (`tests/trainers/test_device_audit.py`).
"""

from __future__ import annotations

import collections
import sys
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode

# Factory calls that place their tensor on the default device unless told otherwise.
FACTORIES = frozenset({torch.zeros, torch.ones, torch.empty, torch.full, torch.arange, torch.rand, torch.randn,
                       torch.randint, torch.randperm, torch.tensor, torch.linspace, torch.eye})
# Reads of a tensor's values by Python: on a GPU each waits for the device (a sync).
HOST_READS = frozenset({torch.Tensor.item, torch.Tensor.tolist, torch.Tensor.numpy, torch.Tensor.__bool__,
                        torch.Tensor.__int__, torch.Tensor.__float__, torch.Tensor.nonzero, torch.nonzero})
PACKAGES = ("jax_env", "torch_kitchen", "trainers")
ROOT = Path(__file__).resolve().parents[1]
OWN_FILE = str(Path(__file__).resolve())


def project_site() -> str:
    """The innermost function of this project's code (not this file's) on the stack, as path:qualified name (a
    function, not a line, so that an edit above it leaves the count's key as it was)."""
    frame = sys._getframe(1)
    while frame is not None:
        name = frame.f_code.co_filename
        if name != OWN_FILE and name.startswith(str(ROOT)) and Path(name).relative_to(ROOT).parts[0] in PACKAGES:
            return f"{Path(name).relative_to(ROOT)}:{frame.f_code.co_qualname}"
        frame = frame.f_back
    return "(outside the project)"


def masks_by_bool(index) -> bool:
    """Whether an index selects by a bool tensor (its result's size is read by the host)."""
    parts = index if isinstance(index, tuple) else (index,)
    return any(isinstance(part, torch.Tensor) and part.dtype == torch.bool for part in parts)


class DeviceAudit(TorchFunctionMode):
    """Counts, while active: `factories` ("zeros at trainers/x.py:f" -> calls without a device) and `host_reads`
    ("item at ...", "bool-index at ..." -> calls)."""

    def __init__(self):
        super().__init__()
        self.factories: collections.Counter[str] = collections.Counter()
        self.host_reads: collections.Counter[str] = collections.Counter()

    def __torch_function__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func in FACTORIES and kwargs.get("device") is None:
            self.factories[f"{func.__name__} at {project_site()}"] += 1
        elif func in HOST_READS:
            self.host_reads[f"{func.__name__} at {project_site()}"] += 1
        elif func is torch.Tensor.__getitem__ and len(args) > 1 and masks_by_bool(args[1]):
            self.host_reads[f"bool-index at {project_site()}"] += 1
        return func(*args, **kwargs)

    def report(self) -> str:
        lines = [f"{sum(self.host_reads.values())} host reads, {sum(self.factories.values())} tensors made without "
                 "a device"]
        lines += [f"  {count:6d} read    {site}" for site, count in self.host_reads.most_common()]
        lines += [f"  {count:6d} made    {site}" for site, count in self.factories.most_common()]
        return "\n".join(lines)


def per_step(short: collections.Counter[str], long: collections.Counter[str], extra_steps: int) -> dict[str, float]:
    """The sites whose count grew between a run and one `extra_steps` steps longer, with their calls per step."""
    return {site: (long[site] - short[site]) / extra_steps for site in long if long[site] > short[site]}
