# hdrcap — the two set-up commands of the README are `make demo` and `make test`.
# Each creates the virtual environment it needs (.venv) and installs the project into it.
PYTHON ?= $(shell command -v python3.11 2>/dev/null || command -v python3)
VENV   := .venv
BIN    := $(VENV)/bin
STAMP  := $(VENV)/.installed

.PHONY: demo test venv bench docs clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[test]'
	touch $(STAMP)

venv: $(STAMP)

## Run the main job on the built-in simulated camera: plan -> capture -> merge -> out/demo.exr
demo: $(STAMP)
	$(BIN)/hdrcap demo --out out --force

## Run the whole test suite
test: $(STAMP)
	$(BIN)/python -m pytest -n 2 -q

## Benchmarks (install peers themselves; print JSON)
bench: $(STAMP)
	$(BIN)/python benchmarks/run_all.py

clean:
	rm -rf $(VENV) out .pytest_cache
