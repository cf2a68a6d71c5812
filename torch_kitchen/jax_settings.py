"""How JAX shares a process with torch: settings read when JAX's first computation starts its device client, so
they take effect as long as they are made before it (importing JAX or `jax_env` computes nothing)."""

from __future__ import annotations

import os

import jax


def share_process_with_torch() -> None:
    """On a GPU, JAX takes memory as it needs it, not 75% of the GPU at its first operation, which would starve
    torch. On the CPU, a step is waited for as soon as it is dispatched: run inline in the calling thread, it skips
    the hand-off to XLA's worker thread and back (10-20% of a collection step at JaxMARL's setting; BENCHMARKS.md).
    Either is left as the user set it: XLA_PYTHON_CLIENT_PREALLOCATE, JAX_CPU_ENABLE_ASYNC_DISPATCH=true."""
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    if "JAX_CPU_ENABLE_ASYNC_DISPATCH" not in os.environ:
        jax.config.update("jax_cpu_enable_async_dispatch", False)
