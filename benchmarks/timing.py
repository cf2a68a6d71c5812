"""Timing helpers shared by the benchmarks."""

from __future__ import annotations

import time
from collections.abc import Callable


def seconds_per_call(call: Callable[[], object], calls: int, warmup: int = 1) -> float:
    """The mean wall time of `calls` calls of `call`, after `warmup` untimed ones (compilation, caches)."""
    for _ in range(warmup):
        call()
    started = time.perf_counter()
    for _ in range(calls):
        call()
    return (time.perf_counter() - started) / calls
