import os
import shutil
import sys
import tempfile
from pathlib import Path

import torch

# Small torch ops slow down 10-100x when two threads compete for the two CI cores.
torch.set_num_threads(1)

# The measuring tools the tests use too (`op_audit`) live with the benchmarks, outside the library's packages;
# searched last, so that the tests' own helper modules come first.
sys.path.append(str(Path(__file__).resolve().parents[1] / "benchmarks"))

# One JAX compilation cache on disk for the whole run: the workers, and the commands, servers and training jobs the
# tests start as processes of their own, compile the same kitchens' programs (the Infinite Kitchen's reset alone takes
# 15-20 s), and each loads what another compiled. A cached program is the one a compilation gives, so results stay
# bit for bit. Set before JAX is imported here; children inherit it; the run that made it removes it.
CACHE = "JAX_COMPILATION_CACHE_DIR"
_own_cache = None
if CACHE not in os.environ:
    _own_cache = os.environ[CACHE] = tempfile.mkdtemp(prefix="kitchen-tests-jax-cache-")
    os.environ.setdefault("JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS", "0.5")  # the programs worth a file


def pytest_unconfigure(config):
    if _own_cache is not None and not hasattr(config, "workerinput"):  # the run's first process, not a worker
        shutil.rmtree(_own_cache, ignore_errors=True)
