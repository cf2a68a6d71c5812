# Two entry points for a fresh machine: `make main` (set up, run the main job) and `make test`.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin

.PHONY: setup main test lint bench

setup: $(VENV)/.installed

# torch is pinned to the CPU build first so the bounded range in setup.cfg never pulls CUDA packages.
$(VENV)/.installed: setup.cfg pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip
	$(BIN)/pip install -q "torch==2.13.0"
	$(BIN)/pip install -q -e ".[test]"
	touch $@

# Trains configs/main.yaml into runs/main/seed0. Called again, it resumes a stopped or killed run, re-evaluates a
# finished one, and starts clean a run killed before its first checkpoint (its partial logs replaced).
MAIN_RUN := runs/main/seed0
main: setup
	if [ -f $(MAIN_RUN)/checkpoints/latest.pt ]; then \
		$(BIN)/kitchen-train --resume $(MAIN_RUN); \
	else \
		$(BIN)/kitchen-train configs/main.yaml; \
	fi

test: setup
	$(BIN)/python -m pytest -q

lint: setup
	$(BIN)/ruff check .

bench: setup
	$(BIN)/python benchmarks/env_step.py
