# Entry points (see README.md): `make run` (the main job: the service flies the SITL field
# experiment), `make test` (the test suite), `make study` (the paper's simulation study),
# `make reliability` (the fault, security and load tests, then docs/reliability.md).
# Each creates and fills the virtual environment .venv when it is missing or out of date.
PYTHON ?= python3
VENV ?= .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
SEEDS ?= 10
OUT ?= out/study

.PHONY: run study test bench reliability clean

$(STAMP): pyproject.toml
	@$(PYTHON) -c 'import sys; sys.exit(0 if sys.version_info >= (3, 11) else "Python >= 3.11 is needed; set PYTHON=python3.11")'
	$(PYTHON) -m venv $(VENV)
	$(BIN)/python -m pip install --quiet --upgrade pip
	$(BIN)/python -m pip install --quiet -e '.[plots,test]'
	touch $(STAMP)

run: $(STAMP)
	$(BIN)/companion-demo field-5-tags --out out/sitl

study: $(STAMP)
	$(BIN)/companion study --seeds $(SEEDS) --out $(OUT)

test: $(STAMP)
	@command -v systemd-analyze >/dev/null || { apt-get update -qq && apt-get install -y -qq systemd >/dev/null; }
	$(BIN)/ruff check .
	$(BIN)/mypy
	$(BIN)/pytest -q

bench: $(STAMP)
	$(BIN)/python benchmarks/bench_filter.py
	$(BIN)/python benchmarks/bench_render.py
	$(BIN)/python benchmarks/bench_pipeline.py

reliability: $(STAMP)
	$(BIN)/pytest -q tests/test_faults_sitl.py tests/test_service_sitl.py tests/test_systemd.py \
		tests/test_soak.py
	$(BIN)/python benchmarks/reliability_report.py

clean:
	rm -rf $(VENV) out .mypy_cache .pytest_cache .ruff_cache
