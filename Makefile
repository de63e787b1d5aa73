# Developer entry points. Everything runs from the venv that scripts/setup.sh maintains.
#   make demo   set up (first time ~1-2 min), then run the demo: no browser, no Node.js, no root
#   make test   set up for the tests (+ Chromium, the Node client of test/foxglove_client), then
#               lint (ruff, lint-imports) + typecheck + docs + pytest; fails if any fails
#   make docs   set up, then build the documentation site (docs/ -> docs/_build/html)
#   make test-quick   set up for the tests, then pytest without the node-graph tests (-m 'not graph')
SHELL := /bin/bash
.SHELLFLAGS := -euo pipefail -c
.DEFAULT_GOAL := help

VENV ?= .venv
BIN := $(VENV)/bin
export HAPTIC_VENV := $(abspath $(VENV))

# The demo: the ROS 2 node graph (simulated maglev, LMI controller, VE, recorder) on the
# paper's Fig. 8 scenario, once with eq. 14 (penalty) and once with eq. 10
# (acceleration_only); each run is recorded to bags/, plotted, and summarised.
define DEMO_CMD
$(BIN)/haptic-topology run fig8 --mode penalty --mode acceleration_only
endef
export DEMO_CMD

PYTEST_ARGS ?=

.PHONY: help setup setup-tests robots test test-quick lint typecheck docs pytest demo bench soak clean colcon-check

help:
	@echo 'make demo       set up the venv and run the demo'
	@echo 'make test       set up, then lint (ruff + layer contracts) + typecheck + docs + pytest'
	@echo 'make docs       set up, then build the Sphinx site: docs/_build/html/index.html'
	@echo 'make test-quick set up, then pytest -m "not graph" (no ROS 2 node processes, no lint)'
	@echo 'make setup      create/update .venv (idempotent, seconds when nothing changed)'
	@echo 'make setup-tests  make setup + what the tests add: Chromium (apt-get), npm ci of test/foxglove_client'
	@echo 'make robots     make setup + the optional extra: example-robot-data (131 MB), robots by name'
	@echo 'make lint | typecheck | pytest   one check (assumes setup)'
	@echo 'make bench      loop, compute and recorder benchmarks -> bench/latest.json'
	@echo 'make soak       an hour of run circle (SOAK_SECONDS=...): every process'"'"'s memory'
	@echo 'make colcon-check  colcon (PyPI) builds the repo in a workspace; the nodes run from it'
	@echo 'make clean      remove .venv and build output'
	@echo 'scripts/stress_tests.sh N [--busy K] [-- PYTEST_ARGS]   pytest N times, K beside a busy core'

setup:
	@bash scripts/setup.sh

# What the tests add to the venv: Chromium (the docs tests render the site) and the Node client
# of the live-view test (Node.js >= 20 with npm). make demo and make docs do without them.
setup-tests:
	@bash scripts/setup.sh --for-tests

# The optional extra "robots": example-robot-data (131 MB) for `linkage: {robot: NAME}` and
# `--linkage robot:NAME` (requirements-robots.lock). Neither setup nor the tests need it.
robots:
	@bash scripts/setup.sh --robots

test: setup-tests
	@$(MAKE) --no-print-directory lint typecheck docs pytest

# The quick loop: every test except those marked `graph` (they start ROS 2 node processes).
test-quick: setup-tests
	$(BIN)/python -m pytest -m 'not graph' $(PYTEST_ARGS)

lint:
	$(BIN)/ruff check .
	$(BIN)/lint-imports --no-cache

typecheck:
	$(BIN)/mypy

# The documentation site (docs/conf.py): every warning is an error (-W, all of them reported:
# --keep-going) and so is every cross-reference that does not resolve (-n, nitpicky). The
# build is offline: no intersphinx, no theme or extension fetched at build time.
DOCS_OUT ?= docs/_build/html
docs: setup
	$(BIN)/sphinx-build -b html -W --keep-going -n -q docs $(DOCS_OUT)
	@echo 'docs: $(DOCS_OUT)/index.html'

# pytest exits 5 when it collects no tests; make treats every non-zero status as failure.
pytest:
	$(BIN)/python -m pytest $(PYTEST_ARGS)

demo: setup
	@eval "$$DEMO_CMD"

# Benchmarks (about 25 min): prints a table, writes bench/latest.json, appends bench/RESULTS.md.
bench: setup
	$(BIN)/python bench/run.py

# A long run (SOAK_SECONDS, default an hour) of `run circle`, then `analyze` of its bag: each
# process's resident set at start and end, peak and slope after the first minute.
SOAK_SECONDS ?= 3600
soak: setup
	$(BIN)/python bench/soak.py --seconds $(SOAK_SECONDS)

# colcon from PyPI in a venv of its own builds a workspace holding this working tree and a node
# runs from its install space (scripts/colcon_check.sh; measured on the shared 2-core machine
# under load: ~4 min the first time, with its venv, then ~2 min).
colcon-check:
	bash scripts/colcon_check.sh

clean:
	rm -rf $(VENV) build install log .pytest_cache .mypy_cache .ruff_cache *.egg-info docs/_build \
		test/foxglove_client/node_modules
	find . -path ./.venv -prune -o -name __pycache__ -type d -prune -exec rm -rf {} +
