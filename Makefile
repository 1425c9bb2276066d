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

# `make run` shows the whole card: the rendezvous as processes with the gtsam smoother and MPC on
# proxsuite (rendezvous_card), then the attitude loop with the magnetorquer board on the CAN bus
# (attitude_quick). `make run SCENARIO=NAME` runs one scenario (`bench scenarios` lists them).
SCENARIO ?=
run: $(STAMP)
ifeq ($(SCENARIO),)
	$(VENV)/bin/bench run rendezvous_card
	$(VENV)/bin/bench run attitude_quick
else
	$(VENV)/bin/bench run $(SCENARIO)
endif

test: $(STAMP)
	bash tools/install-system-deps.sh
	$(PY) -m pytest

benchmarks: $(STAMP)
	for b in benchmarks/bench_*.py; do $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) runs
