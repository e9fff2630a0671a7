# Two entry points: `make demo` (the main job) and `make test` (lint, types, tests).
# Each bootstraps .venv with the pinned dependencies by itself.
PYTHON ?= $(shell command -v python3.11 || command -v python3)
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed-stamp

.PHONY: demo experiment test test-fast lint typecheck pytest bench schemas school clean

$(STAMP): pyproject.toml constraints.txt scripts/bootstrap-venv
	@./scripts/bootstrap-venv "$(PYTHON)" "$(VENV)"
	@touch $@

demo: $(STAMP)
	@mkdir -p out
	$(BIN)/wsnav demo --out out/demo

experiment: $(STAMP)
	@mkdir -p out
	$(BIN)/wsnav experiment --site sites/school --runs 50 --out out/experiment

lint: $(STAMP)
	$(BIN)/ruff check .
	$(BIN)/ruff format --check .

typecheck: $(STAMP)
	$(BIN)/pyright
	cd firmware/device && ../../$(BIN)/pyright -p pyrightconfig.json
	cd firmware/host_stubs && ../../$(BIN)/pyright -p pyrightconfig.json

# The whole suite on TEST_WORKERS processes (pytest-xdist; a module stays on one worker, with its fixtures): most
# tests wait on brokers, robots and browsers, so three share two cores well. A test that fails beside the others
# runs again alone, after them, and is named; one that fails alone fails the run.
TEST_WORKERS ?= 3
pytest: $(STAMP)
	@$(BIN)/pytest -q -n $(TEST_WORKERS) --dist loadfile $(PYTEST_ARGS); rc=$$?; \
	if [ $$rc -eq 5 ]; then echo "pytest: no tests collected"; rc=0; fi; \
	if [ $$rc -eq 1 ]; then \
		echo "pytest: the tests that failed above ran beside others; each runs again alone:"; \
		$(BIN)/pytest -q -p no:xdist --last-failed --last-failed-no-failures none $(PYTEST_ARGS); rc=$$?; \
	fi; exit $$rc

test: lint typecheck pytest

# The tests without real processes (no slow marker): 75 s at load 4.4 (README); `make test` still runs everything.
test-fast: $(STAMP)
	@$(BIN)/pytest -q -m "not slow" $(PYTEST_ARGS); rc=$$?; if [ $$rc -eq 5 ]; then echo "pytest: no tests collected"; rc=0; fi; exit $$rc

schemas: $(STAMP)
	$(BIN)/python -m wsnav.schemas.export

school: $(STAMP)
	$(BIN)/python sites/school/generate.py

bench: $(STAMP)
	@for b in $$(grep -l '__main__' bench/*.py); do m=$$(basename $$b .py); echo "== bench.$$m"; $(BIN)/python -m bench.$$m || exit 1; done

clean:
	rm -rf $(VENV) build out .pytest_cache .ruff_cache
