# Two set-up commands (README): `make demo` and `make test`; `make replicate` runs the measuring
# instrument (Table 3: 8 test scenes x 3 training seeds, about 47 min on two idle cores). Each creates or reuses .venv,
# installs torch==2.13.0 only when no torch is importable (a plain `torch` requirement would pull
# a multi-GB CUDA build), installs the package with its dev extras once, then runs.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.tracegs-installed

.PHONY: setup demo replicate test test-all test-browser lint clean

$(BIN)/python:
	$(PY) -m venv $(VENV)
	$(BIN)/pip install -q --upgrade pip

$(STAMP): $(BIN)/python pyproject.toml
	$(BIN)/python -c "import torch" 2>/dev/null || $(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e ".[dev]"
	touch $(STAMP)

setup: $(STAMP)

demo: setup
	$(BIN)/tracegs-demo

replicate: setup
	$(BIN)/tracegs-replicate

# The suite runs on every core (pytest-xdist, work stealing): each test is single-threaded (tests/conftest.py),
# so two workers on two cores roughly halve the wall time; `pytest FILE` alone still runs in one process.
# The twenty slowest tests close the log: where to look when the suite outgrows its budget.
test: setup
	@$(BIN)/python -m pytest -q -n auto --dist worksteal --durations=20; status=$$?; \
	if [ $$status -eq 5 ]; then echo "make test: pytest collected no tests - the set-up is broken" >&2; fi; \
	exit $$status

test-all: setup
	$(BIN)/python -m pytest -q -m "not gpu"

# The report pages in a real browser: Debian's chromium, installed with apt-get where it is missing (needs root).
test-browser: setup
	@command -v chromium >/dev/null || (apt-get update -q && apt-get install -y -q chromium)
	$(BIN)/python -m pytest -q -n 0 -m browser

lint: setup
	$(BIN)/ruff check tracegs tests benchmarks

clean:
	rm -rf $(VENV) outputs multirun
