# Two commands for a fresh machine: `make demo` and `make test`.
PYTHON ?= python3
VENV := .venv
PY := $(VENV)/bin/python
STAMP := $(VENV)/.installed
AOT := $(VENV)/.kernel-built
KERNEL_SOURCES := planner_core/kernel_jit.py planner_core/window_factor.py planner_core/window_rows.py planner_core/window_kernel.py planner_core/kernel_aot.py planner_core/build_kernel.py

.PHONY: setup demo demo-fleet test lint typecheck pytest bench clean

$(STAMP): pyproject.toml
	test -x $(PY) || $(PYTHON) -m venv $(VENV)
	$(PY) -m pip install --quiet --upgrade pip
	$(PY) -m pip install --quiet -e '.[test,plot]'
	# compile the planner's numba kernel into its cache once (~20 s), not in the first plan that
	# uses it (big CLI plans, benchmarks, tests, `[planner] compiled = true`); the service's own
	# processes and small one-shot plans do without it (benchmarks/footprint.py)
	PLANNER_CORE_KERNEL=jit $(PY) -c "from planner_core.iterative import warm_up; warm_up()"
	touch $(STAMP)

# the kernel's ahead-of-time build (~15-60 s), again whenever its source changes: a plain
# extension module, no numba at run time (planner_core/build_kernel.py), which the service's
# processes plan with; where it cannot be built, they plan on the numpy path (said at start-up)
$(AOT): $(STAMP) $(KERNEL_SOURCES)
	$(PY) -m planner_core.build_kernel || echo "setup: no AOT build of the planner's kernel (reason above)"
	touch $(AOT)

setup: $(STAMP) $(AOT)

demo: setup
	$(PY) -m demo

demo-fleet: setup
	$(PY) -m demo --fleet 3

lint: $(STAMP)
	$(PY) -m ruff check planner_core companion sitl_mock demo tests benchmarks examples

typecheck: $(STAMP)
	$(PY) -m mypy planner_core companion sitl_mock demo

# Three passes, each file's tests in order on one worker (some flights go on from where the last
# one left the vehicle): the CPU-bound maths and unit tests two files at a time; the flights two
# files at a time (they mostly wait on the simulated clock; a CPU-bound file beside a flight
# would starve its planning); then the timing/memory measurements alone (tests/conftest.py SERIAL).
# Every pass runs even when one fails, so that CI shows all.
UNIT := tests/planner tests/companion tests/test_systemd.py tests/test_structure.py
FLIGHTS := tests/mock tests/e2e
pytest: setup
	$(PY) -m pytest -q -n 2 --dist loadfile -m "not serial" $(UNIT); a=$$?; \
	$(PY) -m pytest -q -n 2 --dist loadfile -m "not serial" --durations=12 $(FLIGHTS); b=$$?; \
	$(PY) -m pytest -q -m serial --durations=8 tests; c=$$?; \
	test $$a = 0 && test $$b = 0 && test $$c = 0

test: lint typecheck pytest

bench: setup
	$(PY) -m pip install --quiet -e '.[bench]'
	$(PY) benchmarks/planner.py --quality --minsnap --json out/bench_planner.json
	$(PY) benchmarks/service.py --json out/bench_service.json
	$(PY) benchmarks/footprint.py --json out/bench_footprint.json

clean:
	rm -rf $(VENV) build *.egg-info .pytest_cache .mypy_cache .ruff_cache out planner_core/_window_aot*.so
