import json
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
# The suite's programs run for milliseconds and compile for seconds: LLVM's cheapest optimisation level compiles
# them 2-3x faster (the suite's JAX-heavy files in a quarter less time). The same HLO runs, so the numbers are the ones
# the tests compare as ever; XLA_FLAGS set by the user are kept as they are.
os.environ.setdefault("XLA_FLAGS", "--xla_backend_optimization_level=0")


# Inductor's compiled kernels in a cache per CPU capability: torch's cache does not tell kernels compiled under
# ATEN_CPU_CAPABILITY=avx2 (make test's second pass) from the default ones, and a process that loads the other's
# computes wrong numbers and can corrupt its heap (docs/training.md, "Bit for bit").
os.environ.setdefault("TORCHINDUCTOR_CACHE_DIR", os.path.join(
    tempfile.gettempdir(), f"kitchen-tests-inductor-{os.environ.get('ATEN_CPU_CAPABILITY', 'default').lower()}"))


def pytest_unconfigure(config):
    if _own_cache is not None and not hasattr(config, "workerinput"):  # the run's first process, not a worker
        shutil.rmtree(_own_cache, ignore_errors=True)


# The files in order of their time in the last recorded run, longest first (`make test-durations` records it), so
# that the two workers of `make test` (xdist's loadfile, with its own reordering off) start the long files early
# and end together. Files the record does not know come first, as they may be long.
DURATIONS = Path(__file__).with_name("durations.json")


def pytest_addoption(parser):
    parser.addoption("--record-durations", action="store_true",
                     help=f"write each test file's seconds in this run to {DURATIONS.name} (a full run's)")


def pytest_collection_modifyitems(config, items):
    seconds = json.loads(DURATIONS.read_text()) if DURATIONS.exists() else {}
    items.sort(key=lambda item: -seconds.get(item.nodeid.partition("::")[0], float("inf")))


_recorded: dict[str, float] = {}


def pytest_runtest_logreport(report):
    path = report.nodeid.partition("::")[0]
    _recorded[path] = _recorded.get(path, 0.0) + report.duration


def pytest_sessionfinish(session):
    if session.config.getoption("--record-durations") and not hasattr(session.config, "workerinput"):
        DURATIONS.write_text(json.dumps({path: round(seconds, 1) for path, seconds in
                                         sorted(_recorded.items(), key=lambda entry: -entry[1])}, indent=1) + "\n")
