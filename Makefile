# Two entry points: `make run` (a short training job on this host) and `make test`.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed

.PHONY: setup run test test-containers bench clean

setup: $(STAMP)

# torch is installed first and pinned: an unpinned torch would pull several GB of CUDA wheels.
# Warp's kernels of l2r/RunWarp-v0 compile once here (up to 4 minutes on 2 cores) rather than in
# the first test or run that steps a Warp world.
$(STAMP): pyproject.toml
	$(PYTHON) -m venv $(VENV)
	$(BIN)/pip install --quiet --upgrade pip
	$(BIN)/pip install --quiet torch==2.13.0
	$(BIN)/pip install --quiet -e '.[dev,opensim]'
	$(BIN)/python -m l2r.sim.warp
	touch $(STAMP)

run: setup
	$(BIN)/l2r up

# Two workers, each taking whole files: the suite's end-to-end tests spend half their time waiting on
# daemons they started, so two of them share 2 cores well (about 6 minutes there rather than 10).
test: setup
	$(BIN)/python -m pytest -n 2 --dist loadfile

# The images built and the compose stack run on this machine's container engine (minutes): part of
# `make test` too, which skips them, saying why, where no engine answers (docs/deploy.md).
test-containers: setup
	$(BIN)/python -m pytest -m containers -v

bench: setup
	for b in bench/*.py; do $(BIN)/python $$b || exit 1; done

clean:
	rm -rf $(VENV) runs .pytest_cache
