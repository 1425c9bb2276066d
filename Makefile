# Two commands for a new user: `make run` runs the default bench, `make test` runs the tests.
# Each creates and updates its own virtual environment in .venv from pyproject.toml.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: run test benchmarks clean

$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e '.[test]'
	touch $(STAMP)

# `make run SCENARIO=attitude_quick` shows the attitude card in seconds (default: the bench's own).
SCENARIO ?=
run: $(STAMP)
	$(VENV)/bin/bench run $(SCENARIO)

test: $(STAMP)
	bash tools/install-system-deps.sh
	$(PY) -m pytest

benchmarks: $(STAMP)
	for b in benchmarks/bench_*.py; do $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) runs
