"""What a piece of torch code asks of a GPU, counted on any device: kernel launches and host synchronisations.

On a GPU the fixed costs of small work decide the speed: every operation launches at least one kernel (a few
microseconds of host time each), and every operation whose result the host must read (`.item()`, `bool(tensor)`,
`nonzero`, masked selection) waits until the device has finished everything queued before it. Both show in the
operations torch dispatches, whatever the device: `OpAudit` counts them under a `TorchDispatchMode`, so the
count of a CPU run is the count the same code would give on a GPU (a test can hold the device path to it).

    with OpAudit() as audit:
        policy(tensordict)
    audit.launches, audit.syncs, audit.sync_ops()
"""

from __future__ import annotations

from collections import Counter

import torch
from torch.utils._python_dispatch import TorchDispatchMode

aten = torch.ops.aten

# Operations whose result the host reads before it can go on.
SYNCING = {
    aten._local_scalar_dense.default,  # .item(), float(t), int(t), bool(t) on a one-element tensor
    aten.is_nonzero.default,  # `if tensor:`
    aten.nonzero.default,  # its output's size depends on the data
    aten.masked_select.default,  # likewise: tensor[mask]
    aten.equal.default,  # torch.equal returns a Python bool
    aten._unique2.default,  # torch.unique: likewise
    aten.repeat_interleave.Tensor,  # the output size is the repeats' sum
}
# Operations that allocate or re-describe memory without launching a kernel.
NO_KERNEL = {aten.empty.memory_format, aten.empty_strided.default, aten.empty_like.default}


def _tensors(values) -> list[torch.Tensor]:
    found = []
    for value in values:
        if isinstance(value, torch.Tensor):
            found.append(value)
        elif isinstance(value, (list, tuple)):
            found += _tensors(value)
    return found


class OpAudit(TorchDispatchMode):
    """Counts the operations dispatched inside it (see the module docstring).

    launches: operations that launch at least one kernel (views and bare allocations excluded).
    syncs: operations that make the host wait for the device (`SYNCING`).
    host_tensors: tensors made from Python data (`torch.tensor(...)`): on a GPU, a copy from the host each time.
    transfers: copies between devices (visible where there are two).
    ops: every operation's count by name.
    """

    def __init__(self):
        super().__init__()
        self.ops: Counter[str] = Counter()
        self.launches = self.syncs = self.host_tensors = self.transfers = 0
        self._syncing: Counter[str] = Counter()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        out = func(*args, **kwargs)
        name = str(func.overloadpacket.__name__)
        self.ops[name] += 1
        if func in SYNCING:
            self.syncs += 1
            self._syncing[name] += 1
        if func in (aten.lift_fresh.default, aten.lift_fresh_copy.default):
            self.host_tensors += 1
        elif not func.is_view and func not in NO_KERNEL:
            self.launches += 1
        if func in (aten._to_copy.default, aten.copy_.default):
            devices = {tensor.device for tensor in _tensors([*args, *kwargs.values(), out])}
            self.transfers += len(devices) > 1
        return out

    def sync_ops(self) -> dict[str, int]:
        """The syncing operations seen, by name."""
        return dict(self._syncing)

    def summary(self) -> str:
        syncing = ", ".join(f"{name} x{count}" for name, count in sorted(self._syncing.items())) or "none"
        return (f"{self.launches} launches, {self.syncs} syncs ({syncing}), {self.host_tensors} tensors from host "
                f"data, {self.transfers} device transfers")
