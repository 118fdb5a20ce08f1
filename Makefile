# layoutkit — two commands on a fresh machine: `make demo` and `make test`.
PY ?= python3
VENV := .venv
BIN := $(VENV)/bin
STAMP := $(VENV)/.installed
# pytest with bytecode caching on even where the environment turns it off (PYTHONDONTWRITEBYTECODE, common in
# CI images): every xdist worker otherwise re-runs the assertion rewriting of all test modules (collection
# 7.0 -> 2.7 s per process here) and every `python -m layoutkit` a test starts recompiles the package
PYTEST := PYTHONDONTWRITEBYTECODE= $(BIN)/python -m pytest

.PHONY: venv demo test test-fast test-install durations bench clean

venv: $(STAMP)

$(STAMP): pyproject.toml
	test -x $(BIN)/python || $(PY) -m venv $(VENV)
	$(BIN)/python -m pip install --upgrade pip setuptools wheel
	$(BIN)/python -m pip install -e '.[test]'
	touch $(STAMP)

demo: $(STAMP)
	$(BIN)/python -m layoutkit demo --out-dir out/demo

# the whole suite, slow tests included (what CI runs). Three workers on two cores: ~40 s of each worker's
# time is spent waiting (streams at a real device's pace over ptys, Dask clusters starting), which a third
# worker fills. --dist loadgroup is tests/conftest.py's scheduler: tests handed out one at a time, longest
# files first, except that a module with a module-scoped fixture stays on one worker (built once, not
# once per worker). conftest also pins OpenBLAS to one thread per process: its second thread has no
# core to run on here and spins.
XDIST := -n 3 --dist loadgroup --no-loadscope-reorder
test: $(STAMP)
	$(PYTEST) $(XDIST) -q

# the development loop: slow tests deselected, by mark or by tests/durations.json (< 1 min on 2 idle cores)
test-fast: $(STAMP)
	$(PYTEST) -n 2 --dist loadgroup --no-loadscope-reorder -q -m "not slow and not install"

# re-measure tests/durations.json (which tests test-fast leaves out; the order files run in): the whole suite
durations: $(STAMP)
	LAYOUTKIT_TEST_DURATIONS=tests/durations.json $(PYTEST) $(XDIST) -q

# the wheel installed with every dependency into a fresh venv, then `layoutkit demo` (minutes)
test-install: $(STAMP)
	$(PYTEST) -q -m install tests/test_install.py

bench: $(STAMP)
	$(BIN)/python benchmarks/run_all.py

clean:
	rm -rf out .pytest_cache
