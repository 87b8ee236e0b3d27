# The two commands of the README. Both create ./.venv and install hmflow into it first.
#   make run    - install, then run the main job (a 200-call campaign of the default method, lm, on the built-in synthetic case)
#   make test   - install (with test extras, Debian's OPM `flow`, chromium, slurm-wlm and munge when apt is usable as root), then run the tests
#                 (real OPM, Prefect and Parquet integration tests included; `-m slow` ones are the long sweeps),
#                 two test files at a time (pytest-xdist: the machine's 2 cores; a test's simulations share them)
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
# A path-based editable install (a .pth with the repository root), not setuptools' import hook:
# a Dask worker puts its local directory first on sys.path and spills to <dir>/storage, a
# namespace directory that the import hook never gets to override, so `storage` would not
# import there. On an ordinary sys.path entry the real package wins over a namespace dir.
EDITABLE := --config-settings editable_mode=compat

.PHONY: install install-test run test

install:
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/pip install -q torch==2.13.0
	$(BIN)/pip install -q -e . $(EDITABLE)

install-test: install
	$(BIN)/pip install -q -e '.[test]' $(EDITABLE)
	command -v flow >/dev/null || (command -v apt-get >/dev/null && [ "$$(id -u)" = 0 ] && \
	  DEBIAN_FRONTEND=noninteractive apt-get install -y -q libopm-simulators-bin >/dev/null) || \
	  echo "note: Debian's flow is not installed; the command-line backend tests will be skipped"
	command -v chromium >/dev/null || (command -v apt-get >/dev/null && [ "$$(id -u)" = 0 ] && \
	  (apt-get install -y -q chromium >/dev/null 2>&1 || (apt-get update -q >/dev/null && \
	   DEBIAN_FRONTEND=noninteractive apt-get install -y -q chromium >/dev/null))) || \
	  echo "note: Debian's chromium is not installed; the browser tests of the Prefect UI will be skipped"
	command -v slurmctld >/dev/null || (command -v apt-get >/dev/null && [ "$$(id -u)" = 0 ] && \
	  (DEBIAN_FRONTEND=noninteractive apt-get install -y -q slurm-wlm munge >/dev/null 2>&1 || \
	   (apt-get update -q >/dev/null && \
	    DEBIAN_FRONTEND=noninteractive apt-get install -y -q slurm-wlm munge >/dev/null))) || \
	  echo "note: Debian's slurm-wlm is not installed (or not root); the one-node Slurm tests will be skipped"

run: install
	$(BIN)/hmflow run

test: install-test
	HMFLOW_CACHE_DIR=$$(mktemp -d) PREFECT_HOME=$$(mktemp -d) $(BIN)/python -m pytest -q -m 'not slow' -n 2 --dist loadfile --durations=30
