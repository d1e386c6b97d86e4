# FlyTrack: the one entry point. `make demo` and `make test` set everything up themselves.
# Components add their own targets in mk/<component>.mk (included below).

SHELL := /bin/bash
.DEFAULT_GOAL := help
ROOT := $(abspath .)
VENV := $(ROOT)/.venv
PY := $(VENV)/bin/python
PYTEST := $(PY) -m pytest
BUILD := $(ROOT)/build
JOBS ?= 2
export PYTHONDONTWRITEBYTECODE := 1
# So that the C library built here is found by the host's bindings and tests.
export FLYTRACK_BUILD_DIR := $(BUILD)

# Filled by mk/*.mk
CMAKE_FLAGS :=
TEST_C_TARGETS :=
BENCH_TARGETS :=

.PHONY: help setup build cbuild firmware test test-python test-c test-other-blas test-portability test-load lint format bench demo clean docs docs-serve

help:
	@echo "FlyTrack make targets:"
	@echo "  make demo      the whole rig simulated end to end (DEMO_ARGS='--help' for options)"
	@echo "  make test      set up, build, run every test (C and Python), then lint"
	@echo "  make bench     run every benchmark (BENCH_JSON=PATH writes figures as JSON)"
	@echo "  make test-portability  numerical tests under every OpenBLAS kernel x 1, 2 threads; suite in random order"
	@echo "  make test-load the suite 3 times under a CPU load of twice the cores (stress-ng)"
	@echo "  make docs      build the manual into build/site (docs-serve: serve it on 127.0.0.1:8000)"
	@echo "  make build     build the C parts and the firmware"
	@echo "  make firmware  build the AVR trigger firmware"
	@echo "  make lint      ruff and clang-format checks"
	@echo "  per part:      $(sort $(PART_TARGETS))"

setup:
	@./scripts/setup.sh

cbuild: setup
	@mkdir -p $(BUILD) && cmake -S . -B $(BUILD) -DCMAKE_BUILD_TYPE=RelWithDebInfo $(CMAKE_FLAGS) -Wno-dev > $(BUILD)/cmake.log 2>&1 \
	  || { cat $(BUILD)/cmake.log; exit 1; }
	@set -o pipefail; env -u MAKELEVEL -u MAKEFLAGS -u MFLAGS cmake --build $(BUILD) -j $(JOBS) 2>&1 \
	  | { grep -vE '^\[ *[0-9]+%\]|^-- |^g?make\[[0-9]+\]: (Entering|Leaving)' || true; }

build: cbuild firmware

test: build
	@$(MAKE) --no-print-directory test-c
	@$(MAKE) --no-print-directory test-python
	@$(MAKE) --no-print-directory docs
	@$(MAKE) --no-print-directory test-other-blas
	@$(MAKE) --no-print-directory lint

test-c: cbuild
	@cd $(BUILD) && ctest --output-on-failure -j $(JOBS)

test-python: setup
	@$(PYTEST) -q

# The manual (mkdocs.yml, docs/): strict, so a warning, a broken link or anchor fails the build
# (not --quiet: mkdocs 1.6 then drops the warnings before strict mode counts them).
export NO_MKDOCS_2_WARNING := 1
DOCS_ADDR ?= 127.0.0.1:8000
docs: setup
	@set -o pipefail; $(VENV)/bin/mkdocs build --strict 2>&1 | { grep -v '^INFO ' || true; }
	@echo "docs: built build/site/index.html"

docs-serve: setup
	@$(VENV)/bin/mkdocs serve --strict -a $(DOCS_ADDR)

# The numerical tests again under an OpenBLAS kernel other than this machine's own, so a test whose
# property holds on one kernel only fails here and not on a lab's PC.
test-other-blas: setup
	@$(PY) scripts/test_portability.py --other

# Not in `make test`: the numerical tests under every OpenBLAS core type this CPU runs, at 1 and 2 BLAS
# threads, then the whole suite once in random order; prints the table.
test-portability: build
	@$(PY) scripts/test_portability.py $(PORTABILITY_ARGS)

# Not in `make test`: the whole pytest suite 3 times under stress-ng (twice as many CPU hogs as cores);
# prints the failures per run. LOAD_ARGS='--runs 1 -- host/tests/host' narrows it.
test-load: build
	@FLYTRACK_EXTRA_APT=scripts/apt-packages-load.txt ./scripts/setup.sh
	@$(PY) scripts/test_load.py $(LOAD_ARGS)

lint: setup
	@$(VENV)/bin/ruff check -q host tests && echo "lint: ruff clean"
	@find protocol edge firmware host -name '*.[ch]' -not -path '*/.venv/*' | xargs -r clang-format --dry-run --Werror \
	  && echo "lint: clang-format clean"

format: setup
	@$(VENV)/bin/ruff check --fix host tests || true
	@find protocol edge firmware host -name '*.[ch]' | xargs -r clang-format -i

# Runs every benchmark; with BENCH_JSON=PATH their figures are merged into one JSON file.
bench: build
	@mkdir -p $(BUILD)/bench
	@set -e; for t in $(BENCH_TARGETS); do \
	  $(MAKE) --no-print-directory $$t BENCH_JSON=$(BUILD)/bench/$$t.json; done
	@if [ -n "$(BENCH_JSON)" ]; then \
	  $(PY) scripts/merge_json.py "$(BENCH_JSON)" $(foreach t,$(BENCH_TARGETS),$(BUILD)/bench/$(t).json); fi

# The closed loop runs in the demo too (DEMO_RULES= turns it off).
DEMO_RULES ?= examples/closed_loop.toml
demo: build
	@$(PY) -m flytrack_host.cli demo $(if $(DEMO_RULES),--rules $(DEMO_RULES)) $(DEMO_ARGS)

clean:
	rm -rf $(BUILD)

firmware:
	@true

-include mk/*.mk
