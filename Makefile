# Convoy — `make run` trains (for now: drives the treadmill with the scripted policy), `make test` checks.
# Both create .venv on first use: torch==2.13.0 first (a local CPU wheel on our machines), then the project.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.convoy-installed
OUT    ?= runs/demo

.PHONY: run test lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/convoy env rollout --env treadmill --agents 3 --adversaries 1 --episodes 20 --policy scripted \
		--seed 0 --show 8 --gif $(OUT)/treadmill.gif --summary $(OUT)/summary.json --plot $(OUT)/returns.png

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: lint
	$(BIN)/pytest

bench: $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[dev,bench]'
	$(BIN)/python benchmarks/env_throughput.py --markdown $(OUT)/env_throughput.md

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache .hypothesis
