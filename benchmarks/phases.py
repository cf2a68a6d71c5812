"""Where a training batch's time goes on a device: collection, advantages and update, each as wall time on the
host against the device's busy time (how long the kernels the phase launched kept the device busy, overlaps counted
once), under `torch.profiler`.

Runs `trainers.ppo.loop.train_teams` on a setting of `benchmarks/jax_ppo.py` and labels its three phases from outside
(the collector's batches, `start_update`, which holds GAE, and `update_teams`), so the trainer runs as it always
does. Where busy time is far below wall time, the host (Python, launches, syncs) is what the phase waits on. The
first update compiles and is left out. On a CPU the device columns are empty.

    python benchmarks/phases.py [--setting protocol] [--updates 3] [--device cuda] [key=value ...]
"""

from __future__ import annotations

import argparse
import functools
import math
import tempfile
from collections import defaultdict
from dataclasses import dataclass

import torch
from jax_ppo import SETTINGS, setting_overrides  # with the test extra
from torch.autograd import DeviceType
from torch.profiler import ProfilerActivity, profile, record_function

import trainers.ppo.loop
import trainers.ppo.team
from trainers.config.compose import load_config
from trainers.machine import machine_name

PHASES = ("collection", "advantages", "update")


def labelled(function, label: str):
    """`function` run inside a profiler range named `label`."""

    @functools.wraps(function)
    def run(*args, **kwargs):
        with record_function(label):
            return function(*args, **kwargs)

    return run


class LabelledCollector:
    """A collector whose every batch is gathered inside a profiler range named "collection"."""

    def __init__(self, collector):
        self.collector = collector

    def __iter__(self):
        batches = iter(self.collector)
        while True:
            with record_function("collection"):
                batch = next(batches, None)
            if batch is None:
                return
            yield batch

    def shutdown(self):
        self.collector.shutdown()


def phase_seconds(setting: str, updates: int, device: str, overrides: list[str]) -> dict[str, list[float]]:
    """Per phase: [wall seconds, device busy seconds], summed over updates 2..`updates` (all teams)."""
    make_collector = trainers.ppo.loop.make_collector
    patched = {  # (where, name): the labelled stand-in
        (trainers.ppo.loop, "make_collector"):
            lambda *args, **kwargs: LabelledCollector(make_collector(*args, **kwargs)),
        (trainers.ppo.loop, "start_update"): labelled(trainers.ppo.loop.start_update, "advantages"),
        (trainers.ppo.loop, "update_teams"): labelled(trainers.ppo.loop.update_teams, "update"),
    }
    originals = {target: getattr(*target) for target in patched}
    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.startswith("cuda") else [])
    frames = load_config(None, [*setting_overrides(setting), *overrides]).frames_per_batch  # per team
    totals = defaultdict(lambda: [0.0, 0.0])
    with tempfile.TemporaryDirectory() as run_dir:
        config = load_config(None, [*setting_overrides(setting), f"total_steps={updates * frames}",
                                    f"runtime.device={device}", f"run_dir={run_dir}", "progress=false",
                                    "eval_episodes=0",
                                    "checkpoint_every=1000", "runtime.threads=1", *overrides])
        try:
            for (where, name), function in patched.items():
                setattr(where, name, function)
            with profile(activities=activities) as profiler:
                trainers.ppo.loop.train_teams(trainers.ppo.team.team_configs(config))
        finally:
            for (where, name), function in originals.items():
                setattr(where, name, function)
    first_update = {"collection": 1, "advantages": config.runtime.teams, "update": 1}  # its ranges, left out
    spans = [Span.of(event) for event in profiler.profiler.kineto_results.events()]
    seen, timed = defaultdict(int), []
    for span in sorted(spans, key=lambda span: span.start):
        if span.name in PHASES and not span.on_device:
            seen[span.name] += 1
            if seen[span.name] > first_update[span.name]:
                timed.append(span)
                totals[span.name][0] += (span.end - span.start) / 1e9
    for phase, busy in busy_seconds(spans, timed).items():
        totals[phase][1] = busy
    return totals


@dataclass(frozen=True)
class Span:
    """One profiler event, host or device, in nanoseconds: what `busy_seconds` reads of it."""

    name: str
    id: int  # a host event's correlation id
    launcher: int  # a kernel's: the id of the host event that launched it (0: none)
    start: int
    end: int
    on_device: bool
    annotation: bool  # a host range drawn again on the device's timeline, not a kernel

    @classmethod
    def of(cls, event) -> Span:
        """From a Kineto event (`profile().profiler.kineto_results.events()`)."""
        return cls(event.name(), event.correlation_id(), event.linked_correlation_id(), event.start_ns(),
                   event.start_ns() + event.duration_ns(), event.device_type() != DeviceType.CPU,
                   event.is_user_annotation())


def busy_seconds(spans: list[Span], ranges: list[Span]) -> dict[str, float]:
    """Per phase: the seconds the device was busy with the kernels launched inside that phase's `ranges` (host
    ranges), overlapping kernels counted once. (A range's `device_time_total` counts a kernel again under every
    nested range that the device's timeline annotates, and reads above wall time.)"""
    launched = {span.id: span.start for span in spans if not span.on_device}
    intervals = defaultdict(list)
    for kernel in spans:
        start = launched.get(kernel.launcher) if kernel.on_device and not kernel.annotation else None
        phase = next((r.name for r in ranges if start is not None and r.start <= start <= r.end), None)
        if phase is not None:
            intervals[phase].append((kernel.start, kernel.end))
    busy = {}
    for phase, kernels in intervals.items():
        total, reached = 0, -math.inf
        for start, end in sorted(kernels):
            total += max(0, end - max(start, reached))
            reached = max(reached, end)
        busy[phase] = total / 1e9
    return busy


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--setting", choices=list(SETTINGS), default="protocol")
    parser.add_argument("--updates", type=int, default=3)
    parser.add_argument("--device", default="cpu")
    parser.add_argument("overrides", nargs="*", help="config overrides, key=value")
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    totals = phase_seconds(args.setting, args.updates, args.device, args.overrides)
    timed = args.updates - 1
    print(f"setting {args.setting}, {args.device}, {machine_name()}; seconds per batch over updates 2..{args.updates}")
    print(f"{'phase':<12s} {'wall s':>8s} {'device busy s':>14s} {'busy / wall':>12s}")
    for phase in PHASES:
        wall, busy = (value / timed for value in totals[phase])
        print(f"{phase:<12s} {wall:8.3f} {busy:14.3f} {busy / wall if wall else 0:12.2f}")


if __name__ == "__main__":
    main()
