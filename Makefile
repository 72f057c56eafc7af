# Every target works from a fresh clone: it creates .venv and installs what it needs.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: demo test bench lint clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet -e ".[dev]"
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python examples/swinging_chain.py
	$(BIN)/python examples/ragdoll_demo.py

test: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/python -m pytest -v --durations=10

bench: $(STAMP)
	$(BIN)/python benchmarks/chain_throughput.py

lint: $(STAMP)
	$(BIN)/ruff check . && $(BIN)/ruff format --check .

clean:
	rm -rf $(VENV) demo_output .pytest_cache
