# Two commands for a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed

.PHONY: setup demo demo-fleet test lint typecheck pytest bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,plot]'
	# compile the planner's numba kernel into its cache once (~20 s), not in the first plan that
	# uses it (big CLI plans, benchmarks, tests, `[planner] compiled = true`); the service's own
	# processes and small one-shot plans do without it (benchmarks/footprint.py)
	$(PY) -c "from planner_core.iterative import warm_up; warm_up()"
	touch $(STAMP)

setup: $(STAMP)

demo: $(STAMP)
	$(PY) -m demo

demo-fleet: $(STAMP)
	$(PY) -m demo --fleet 3

lint: $(STAMP)
	$(PY) -m ruff check planner_core companion sitl_mock demo tests benchmarks examples

typecheck: $(STAMP)
	$(PY) -m mypy planner_core companion sitl_mock demo

# Two passes: everything but the timing/memory measurements two files at a time (a file's tests
# keep their order on one worker: some flights go on from where the last one left the
# vehicle), then those measurements alone.
pytest: $(STAMP)
	$(PY) -m pytest -q -n 2 --dist loadfile -m "not serial"; a=$$?; \
	$(PY) -m pytest -q -m serial; b=$$?; \
	test $$a = 0 && test $$b = 0

test: lint typecheck pytest

bench: $(STAMP)
	$(PY) -m pip install --quiet -e '.[bench]'
	$(PY) benchmarks/planner.py --quality --minsnap --json out/bench_planner.json
	$(PY) benchmarks/service.py --json out/bench_service.json
	$(PY) benchmarks/footprint.py --json out/bench_footprint.json

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache out
