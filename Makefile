# fleetbrake — `make help` lists the targets.
SHELL := /bin/bash
.DEFAULT_GOAL := help

VENV ?= .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.fleetbrake-installed
DEMO_OUT ?= demo-out
export CARGO_TERM_COLOR ?= never

.PHONY: help setup build wheel demo test test-all test-rust test-python lint format docs bench rom-data clean

help:  ## list the targets
	@grep -hE '^[a-zA-Z_-]+:.*## ' $(MAKEFILE_LIST) | awk 'BEGIN {FS = ":.*## "} {printf "  %-12s %s\n", $$1, $$2}'

# The tests' MQTT broker is Debian's mosquitto (installed here when missing; CI runs as root).
$(STAMP): pyproject.toml
	command -v mosquitto >/dev/null || test -x /usr/sbin/mosquitto || (apt-get update -q && DEBIAN_FRONTEND=noninteractive apt-get install -y -q --no-install-recommends mosquitto)
	test -x $(PY) || python3 -m venv $(VENV)
	$(PY) -m pip install -q --upgrade pip
	$(PY) -m pip install -q -e ".[dev]"
	touch $(STAMP)

setup: $(STAMP)  ## create .venv and install fleetbrake with its dev tools

build: setup  ## (re)build the Rust extension into .venv (release)
	# maturin develop installs into the active virtualenv ($$VIRTUAL_ENV) before ./.venv: name ours
	VIRTUAL_ENV=$(abspath $(VENV)) $(VENV)/bin/maturin develop --release -q

# The wheel a user installs (release build, SQL and type stubs inside); the wheel test installs
# it into a fresh virtualenv outside the checkout.
WHEEL_DIR := dist
wheel: setup  ## build the wheel into dist/ (what users install)
	rm -f $(WHEEL_DIR)/fleetbrake-*.whl
	$(VENV)/bin/maturin build --release -q --out $(WHEEL_DIR)

# --force: `make demo` again replaces the previous demo's results; it wipes only a directory a
# demo made (or an empty one), never anything else (docs/demo.md).
demo: build  ## synthetic fleet through the whole pipeline into $(DEMO_OUT)/ (again: replaced)
	$(VENV)/bin/fleetbrake demo --out $(DEMO_OUT) --force

test: build test-rust test-python  ## every test that matters (slow ones skipped)

# The test runners keep both cores busy (two test threads, two pytest workers): the kernels'
# own threads (rayon: two-thread triangular solves, reduced-model batches) would only wait
# for each other, so the tests run them on one.
TEST_ENV := RAYON_NUM_THREADS=1

test-rust:  ## Rust unit and integration tests
	$(TEST_ENV) cargo test --release --workspace --exclude fleetbrake_py

test-python: build wheel  ## Python tests, slow ones skipped (the wheel test included)
	$(TEST_ENV) FLEETBRAKE_TEST_WHEEL="$$(ls $(abspath $(WHEEL_DIR))/fleetbrake-*.whl)" $(PY) -m pytest -m "not slow" -n 2 -q

test-all: build wheel test-rust  ## every test, slow ones included
	$(TEST_ENV) FLEETBRAKE_TEST_WHEEL="$$(ls $(abspath $(WHEEL_DIR))/fleetbrake-*.whl)" $(PY) -m pytest -n 2 -q

# tools/check_repo.py: module, function and crate-file sizes, and no work-period names,
# internal tags, issue numbers or scratch paths in docs, code and tests.
lint: setup  ## rustfmt, clippy, ruff, mypy, import-linter and tools/check_repo.py, as CI runs them
	cargo fmt --all -- --check
	cargo clippy --workspace --all-targets --release -- -D warnings
	$(VENV)/bin/ruff check python tests tools
	$(VENV)/bin/ruff format --check python tests tools
	$(VENV)/bin/mypy
	$(VENV)/bin/lint-imports
	$(PY) tools/check_repo.py

format: setup  ## format Rust and Python in place
	cargo fmt --all
	$(VENV)/bin/ruff format python tests tools
	$(VENV)/bin/ruff check --fix python tests tools

# The configuration reference is generated from the configuration classes' docstrings
# (fleetbrake.cli.configref); tests/test_configref.py fails when the file is out of date.
docs: setup  ## regenerate docs/configuration.md from the configuration classes
	$(VENV)/bin/fleetbrake config > docs/configuration.md.new \
		&& mv docs/configuration.md.new docs/configuration.md \
		|| { rm -f docs/configuration.md.new; exit 1; }

rom-data: setup  ## rebuild the reduced models the package ships (python/fleetbrake/model/data)
	$(PY) -m fleetbrake.model.romdata

bench: build  ## the solver benchmark against scikit-fem (see docs/benchmarks.md)
	$(VENV)/bin/fleetbrake bench solver --json

clean:  ## remove build products and the virtualenv
	cargo clean
	rm -rf $(VENV) $(DEMO_OUT) $(WHEEL_DIR) .pytest_cache .ruff_cache .mypy_cache .import_linter_cache
