# Every target works from a fresh clone: it creates .venv and installs what it needs.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test test-slow test-all bench lint clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e ".[dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python examples/swinging_chain.py
	$(BIN)/python examples/ragdoll_demo.py

# The CI suite: everything but the tests marked slow (about 20 minutes on 2 cores).
test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -v --durations=15 -m "not slow"

# The long physics checks (10,000-step ragdoll, chain gaps over 5 s, stacks, training runs).
test-slow: $(STAMP)
	$(BIN)/python -m pytest -v --durations=15 -m slow

test-all: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -v --durations=15

# Quick by default; `make bench FULL=1` for batches up to 4096 and 1000-step gradients.
bench: $(STAMP)
	$(BIN)/python benchmarks/chain_throughput.py
	$(BIN)/python benchmarks/brax_comparison.py $(if $(FULL),--full,)

lint: $(STAMP)
	$(BIN)/ruff check . && $(BIN)/ruff format --check .

clean:
	rm -rf $(VENV) demo_output .pytest_cache
