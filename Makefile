# Two entry points for a fresh machine: `make main` (set up, run the main job) and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup main test test-durations lint bench gpu-offline

# DEVICE=cuda: the CUDA builds of torch and JAX, and the main job on the GPU (`make main DEVICE=cuda`).
DEVICE ?= cpu
# The JAX CUDA plugin to install with DEVICE=cuda (jax[cuda12] for a driver older than CUDA 13's).
JAX_CUDA ?= cuda13
STAMP := $(VENV)/.installed-$(DEVICE)

setup: $(STAMP)

# CPU: torch is pinned to the CPU build first so the bounded range in setup.cfg never pulls CUDA packages.
# CUDA: PyPI's Linux torch wheel is the CUDA build; JAX gets the CUDA plugin of the same JAX version.
$(STAMP): setup.cfg pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	rm -f $(VENV)/.installed-*
	$(BIN)/pip install -q "torch==2.13.0"
	$(BIN)/pip install -q -e ".[test]"
	if [ "$(DEVICE)" = cuda ]; then \
		$(BIN)/pip install -q "jax[$(JAX_CUDA)]==$$($(BIN)/python -c 'import jax; print(jax.__version__)')"; \
		$(BIN)/python -c 'import torch, jax; assert torch.cuda.is_available(), "this torch has no CUDA (a CPU build from an earlier set-up? remove .venv and run make again)"; print("torch", torch.__version__, torch.cuda.get_device_name(0), "| jax", jax.devices())'; \
	fi
	touch $@

# Trains configs/main.yaml into runs/main/seed0. Called again, it resumes a stopped or killed run, re-evaluates a
# finished one, and starts clean a run killed before its first checkpoint (its partial logs replaced).
MAIN_RUN := runs/main/seed0
main: setup
	if [ -f $(MAIN_RUN)/checkpoints/latest.pt ]; then \
		$(BIN)/kitchen-train --resume $(MAIN_RUN); \
	else \
		$(BIN)/kitchen-train configs/main.yaml runtime.device=$(DEVICE); \
	fi

# The bit-for-bit tests run a second time with every library held to AVX2 kernels (torch's own, oneDNN's, MKL's and
# XLA's), so that a machine with AVX-512 checks what one without computes (docs/training.md, "Bit for bit"); each
# capability keeps its own Inductor cache (tests/conftest.py).
AVX2 := ATEN_CPU_CAPABILITY=avx2 ONEDNN_MAX_CPU_ISA=AVX2 MKL_ENABLE_INSTRUCTIONS=AVX2 \
	XLA_FLAGS="--xla_cpu_max_isa=AVX2 --xla_backend_optimization_level=0"
# The browser test of kitchen-play drives Debian's Chromium: installed here where apt can, skipped (saying so) elsewhere.
# The suite runs on TEST_WORKERS processes (pytest-xdist), each test file on one of them, torch on one thread each.
TEST_WORKERS ?= 2
test: setup
	@command -v chromium >/dev/null || ! command -v apt-get >/dev/null || \
		(apt-get install -y -q chromium || (apt-get update -q && apt-get install -y -q chromium)) >/dev/null 2>&1 || \
		echo "no Chromium could be installed: the browser test will be skipped"
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder --durations=10
	$(AVX2) $(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder -m bitwise

# tests/durations.json, the order in which make test hands its files to the workers: each file's seconds in a full run.
test-durations: setup
	$(BIN)/python -m pytest -q -n $(TEST_WORKERS) --dist loadfile --no-loadscope-reorder --record-durations

# .whl/ for benchmarks/gpu_checks.sh on a GPU machine without a package index: TorchRL's wheels from WHEELS, and
# copies of the pure-Python packages such a machine may lack, taken from this set-up without their compiled parts
# (each has a pure-Python fallback). Name .whl in the device run's carried paths.
WHEELS ?= ../shared/gpu
OFFLINE_PACKAGES := omegaconf antlr4 yaml hydra hydra_plugins tqdm flax optax absl msgpack rich attr markdown_it mdurl pygments
gpu-offline: setup
	rm -rf .whl && mkdir -p .whl/site && cp $(WHEELS)/*.whl .whl/
	site=$$($(BIN)/python -c 'import sysconfig; print(sysconfig.get_paths()["purelib"])'); \
		for package in $(OFFLINE_PACKAGES); do cp -r $$site/$$package .whl/site/; done
	find .whl/site \( -name '*.so' -o -name __pycache__ \) -prune -exec rm -rf {} +

lint: setup
	$(BIN)/ruff check .

bench: setup
	$(BIN)/python benchmarks/env_step.py
