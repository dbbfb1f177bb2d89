# Convoy — `make run` trains MA-MeSN on the treadmill (2 actor processes + a learner over Zenoh), `make test` checks.
# Both create .venv on first use: torch==2.13.0 first (a local CPU wheel on our machines), then the project.
PYTHON ?= python3
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.convoy-installed
OUT    ?= runs/demo

.PHONY: run run-inprocess serve demo test lint bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet torch==2.13.0
	$(BIN)/python -m pip install --quiet -e '.[dev]'
	touch $(STAMP)

STEPS  ?= 100000

ACTORS ?= 2

run: $(STAMP)
	$(BIN)/convoy train --algo ma-mesn --env treadmill --actors $(ACTORS) --steps $(STEPS) --seed 0 --out $(OUT)

run-inprocess: $(STAMP)
	$(BIN)/convoy train --inprocess --algo ma-mesn --env treadmill --steps $(STEPS) --seed 0 --out $(OUT)-inprocess

serve: $(STAMP)
	$(BIN)/convoy serve --port $(or $(PORT),8000) --data runs/service

demo: $(STAMP)
	$(BIN)/convoy env rollout --env treadmill --agents 3 --adversaries 1 --episodes 20 --policy scripted \
		--seed 0 --show 8 --gif $(OUT)/treadmill.gif --summary $(OUT)/summary.json --plot $(OUT)/returns.png

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

test: lint
	$(BIN)/pytest

bench: $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[dev,bench]'
	$(BIN)/python benchmarks/env_throughput.py --markdown runs/bench/env_throughput.md
	$(BIN)/python benchmarks/learner_throughput.py --markdown runs/bench/learner_throughput.md
	$(BIN)/python benchmarks/inference_scaling.py --markdown runs/bench/inference_scaling.md
	$(BIN)/python benchmarks/speaker_listener.py --json runs/bench/speaker_listener.json
	$(BIN)/python benchmarks/runtime.py --markdown runs/bench/runtime.md
	$(BIN)/python benchmarks/decentralized.py --json runs/bench/decentralized.json --plot runs/bench/decentralized.png

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache .hypothesis
