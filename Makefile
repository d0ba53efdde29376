# DroneFL: `make demo` runs the default experiment, `make test` the test suite.
# Both create .venv and install the project into it when needed.
PYTHON ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.dronefl-installed
export MPLBACKEND := Agg
export FLWR_TELEMETRY_ENABLED := 0
export YOLO_OFFLINE := 1

.PHONY: install demo test lint format bench clean

$(STAMP): pyproject.toml constraints.txt
	test -x $(BIN)/python || $(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install -c constraints.txt -e ".[dev]"
	touch $(STAMP)

install: $(STAMP)

demo: install
	$(BIN)/dronefl demo --out runs/demo

test: install lint
	$(BIN)/python -m pytest -n auto --dist loadfile --no-loadscope-reorder

lint: install
	$(BIN)/ruff check dronefl tests benchmarks examples
	$(BIN)/ruff format --check dronefl tests benchmarks examples
	$(BIN)/lint-imports --no-cache

format: install
	$(BIN)/ruff format dronefl tests benchmarks examples
	$(BIN)/ruff check --fix dronefl tests benchmarks examples

bench: install
	$(BIN)/dronefl bench --out runs/bench

clean:
	rm -rf $(VENV) runs .pytest_cache .ruff_cache
