# Two commands for a new user: `make run` runs the default bench, `make test` runs the tests.
# Each creates and updates its own virtual environment in .venv from pyproject.toml.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: run test studies benchmarks clean lock bytecode

# The environment is installed from requirements.lock (every version pinned, with hashes), so a fresh
# clone runs what was tested; pyproject.toml keeps the open ranges for those who install the package
# as a library. `make lock` recompiles the lock after a change to pyproject.toml, keeping every pin it
# can; `make lock UPGRADE=--upgrade` moves every package to its newest allowed version.
# pip compiles every installed file to bytecode (about 25 s of the install): where
# PYTHONDONTWRITEBYTECODE is set (as on the project's CI machine) Python never writes the bytecode
# it compiles on import, and every node process, report and test would compile matplotlib, scipy
# and ray from source again (the imports of a node: 3.9-5.4 s without bytecode, 1.6-2.0 s with).
$(STAMP): pyproject.toml requirements.lock
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q --require-hashes -r requirements.lock
	$(PY) -m pip install -q --no-deps -e .
	$(PY) tools/check_lock.py
	touch $(STAMP)

# pip compiled the installed packages, but not this checkout (installed editable): where
# PYTHONDONTWRITEBYTECODE is set, every launcher, zygote, node and `bench` command of a test run
# would compile bench/ from source again (about 0.5 s of CPU a run, 120 runs in `make test`).
# compileall writes the bytecode whatever that variable says, and only for files changed since.
bytecode: $(STAMP)
	$(PY) -m compileall -q bench tests benchmarks examples tools

lock:
	$(PYTHON) -m venv $(VENV)
	$(PY) -m pip install -q uv
	$(VENV)/bin/uv pip compile pyproject.toml --extra test --extra cluster --generate-hashes $(UPGRADE) \
		--python-version 3.11 --python-platform x86_64-unknown-linux-gnu -o requirements.lock

# `make run` shows the whole card: the rendezvous as processes with the gtsam smoother and MPC on
# proxsuite (rendezvous_card), then the attitude loop with the magnetorquer board on the CAN bus
# (attitude_quick). `make run SCENARIO=NAME` runs one scenario (`bench scenarios` lists them).
SCENARIO ?=
UPGRADE ?=
run: bytecode
ifeq ($(SCENARIO),)
	$(VENV)/bin/bench run rendezvous_card
	$(VENV)/bin/bench run attitude_quick
else
	$(VENV)/bin/bench run $(SCENARIO)
endif

test: bytecode
	bash tools/install-system-deps.sh
	$(PY) tools/check_lock.py
	$(PY) -m pytest --durations=25

# The long studies the default test run leaves out (pytest's `study` mark, pyproject.toml): orbits
# of simulated time, IPOPT on the larger problems, the attitude fault run over the kernel's CAN.
studies: bytecode
	bash tools/install-system-deps.sh
	$(PY) -m pytest -m study --durations=25

benchmarks: bytecode
	for b in benchmarks/bench_*.py; do $(PY) $$b || exit 1; done

clean:
	rm -rf $(VENV) runs
