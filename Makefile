# HandFE: `make demo` and `make test` set up everything they need by themselves (idempotent).
SHELL := /bin/bash
VENV  := .venv
PY    := $(VENV)/bin/python
STAMP := $(VENV)/.handfe-installed
NP    ?= 2
# Open MPI refuses to run as root unless told so; a normal user needs nothing.
MPIRUN := mpirun -n $(NP) $(if $(filter 0,$(shell id -u)),--allow-run-as-root,)
export OMP_NUM_THREADS ?= 1
export OPENBLAS_NUM_THREADS ?= 1
export MPLBACKEND ?= Agg

.PHONY: setup system demo test test-serial test-mpi lint clean

setup: system $(STAMP)

system:
	@bash scripts/install-system.sh

$(STAMP): pyproject.toml
	@# a venv without pip is one whose creation was interrupted: made again from scratch
	@$(PY) -m pip --version >/dev/null 2>&1 || \
		/usr/bin/python3 -m venv --clear --system-site-packages $(VENV)
	$(PY) -m pip install -q --disable-pip-version-check -e '.[test]'
	@$(PY) scripts/check-env.py
	@touch $(STAMP)

demo: setup
	$(MPIRUN) $(VENV)/bin/handfe demo

# MPI-2 regression tests first, then the full serial suite (whose pytest summary ends the log).
test: setup
	@$(MAKE) --no-print-directory test-mpi
	@$(MAKE) --no-print-directory test-serial

test-serial:
	$(PY) -m pytest -q tests

test-mpi:
	$(MPIRUN) $(PY) scripts/mpi-pytest.py -q -m mpi tests

lint: setup
	$(VENV)/bin/ruff check handfe tests benchmarks scripts

clean:
	rm -rf $(VENV) *.egg-info .pytest_cache
