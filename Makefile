# Entry points (see README.md): `make run` (the main job: the service flies the SITL field
# experiment), `make test` (the test suite), `make check` (lint, types and the tests that fly
# no SITL mission and start no browser: the fast tier), `make study` (the paper's simulation study;
# `make study PLANNERS=lawnmower,search-track` adds the planners side by side),
# `make reliability` (the fault, security and load tests, then docs/reliability.md),
# `make lock` (regenerates requirements/onboard.lock, the hashed onboard install).
# Each creates and fills the virtual environment .venv when it is missing or out of date.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
SEEDS ?= 10
OUT ?= out/study
PLANNERS ?=

LOCK := requirements/onboard.lock
LOCK_VENV ?= /tmp/companion-lock-venv
LOCK_FLAGS ?=

.PHONY: run study test check bench reliability lock clean

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "Python >= 3.11 is needed; set PYTHON=python3.11")'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[plots,test]'
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/companion-demo field-5-tags --out out/sitl

study: $(STAMP)
	$(BIN)/companion study --seeds $(SEEDS) --out $(OUT) $(if $(PLANNERS),--planners $(PLANNERS))

test: $(STAMP)
	@command -v systemd-analyze >/dev/null || { apt-get update -qq && apt-get install -y -qq systemd >/dev/null; }
	@test -x /usr/bin/chromium || { apt-get update -qq && apt-get install -y -qq chromium >/dev/null; }
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/pytest -q

check: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/pytest -q -m "not sitl and not browser"

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_filter.py
	$(BIN)/python benchmarks/bench_render.py
	$(BIN)/python benchmarks/bench_pipeline.py

reliability: $(STAMP)
	$(BIN)/pytest -q tests/test_faults_sitl.py tests/test_service_sitl.py tests/test_systemd.py \
		tests/test_soak.py tests/test_view_load_sitl.py
	$(BIN)/python benchmarks/reliability_report.py

# The runtime dependencies of pyproject.toml pinned with their hashes, for Python 3.11 on linux
# x86_64; the compiler lives in a throwaway virtual environment, not in $(VENV). It keeps the
# pins already in the lock that still fit; `make lock LOCK_FLAGS=--upgrade` takes the newest.
lock:
	$(PYTHON) -m venv $(LOCK_VENV)
	$(LOCK_VENV)/bin/python -m pip install --quiet pip-tools
	CUSTOM_COMPILE_COMMAND="make lock" $(LOCK_VENV)/bin/pip-compile --quiet --generate-hashes \
		--strip-extras --no-emit-index-url --no-emit-find-links --output-file $(LOCK) $(LOCK_FLAGS) pyproject.toml

clean:
	rm -rf $(VENV) out .mypy_cache .pytest_cache .ruff_cache
