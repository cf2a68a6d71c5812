"""The machine a measurement ran on, as benchmark and result tables name it."""

from __future__ import annotations

import os
import platform
import subprocess
from pathlib import Path


def processor_name() -> str:
    """The CPU's model name where Linux tells it (platform.processor() says only "x86_64" there)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.partition(":")[2].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine()


def usable_cores() -> int:
    """The CPU cores this process may run on (its affinity where the OS tells it, e.g. under SLURM or taskset)."""
    if hasattr(os, "sched_getaffinity"):  # Linux
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def machine_name() -> str:
    """The CPU's model name and the cores this process may use, e.g. "AMD EPYC, 2 cores"."""
    return f"{processor_name()}, {usable_cores()} cores"


def code_version(root: Path = Path(__file__).resolve().parents[1]) -> str:
    """The commit of the code in `root` (this project's checkout), "-dirty" where files differ from it; "unknown"
    outside a git checkout (an installed copy)."""
    try:
        described = subprocess.run(["git", "describe", "--always", "--dirty", "--abbrev=10"], cwd=root,
                                   capture_output=True, text=True, timeout=30)
    except (OSError, subprocess.TimeoutExpired):
        return "unknown"
    return described.stdout.strip() if described.returncode == 0 and described.stdout.strip() else "unknown"


# The benchmarks' --threads help: why their default is one torch thread, as the trainer's is.
THREADS_HELP = ("torch threads (default 1, which holds its speed beside other work; 2 collapse to a quarter of "
                "their speed when another process takes a core: BENCHMARKS.md)")
