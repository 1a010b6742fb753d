# hdrcap — the two set-up commands of the README are `make demo` and `make test`.
# Each creates the virtual environment it needs (.venv) and installs the project into it.
PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test lint typecheck venv bench clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

## Run the main job on the built-in simulated camera: plan -> capture -> merge -> out/demo.exr
## (the merge kernels compiled first: once after an install, then loaded from numba's cache)
demo: $(STAMP)
	$(BIN)/hdrcap warm-up
	$(BIN)/hdrcap demo --out out --force

## Lint and format check (ruff), type check (mypy; both configured in pyproject.toml), then the whole test suite
test: lint typecheck
	$(BIN)/python -m pytest -n 2 -q

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

## mypy on the package as installed (hdrcap.*): tools/typecheck.py lays it out under build/typecheck
typecheck: $(STAMP)
	$(BIN)/python tools/typecheck.py

## Benchmarks (install peers themselves; print JSON)
bench: $(STAMP)
	$(BIN)/python -m pip install --quiet -e '.[test,bench]'
	$(BIN)/python benchmarks/run_all.py

clean:
	rm -rf $(VENV) out .pytest_cache build/typecheck
