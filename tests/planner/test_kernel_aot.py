"""The compiled pass's ahead-of-time build (`python -m planner_core.build_kernel`): it loads
without numba, plans exactly as numba's JIT build of the same source, and a build of another
source is refused with the reason. Real plans on both builds; skipped only where the AOT build
is absent (a setup whose build failed: plans then use the JIT, as before it)."""

from __future__ import annotations

import json
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from planner_core import IterativeOptions, kernel_aot, window
from planner_core.iterative import plan_iterative
from planner_core.jets import ProblemCache
from planner_core.window import jet_scales
from tests.planner.test_window import _problem

ROOT = Path(__file__).resolve().parents[2]

pytestmark = pytest.mark.skipif(
    kernel_aot.built_path() is None,
    reason=f"the AOT build of the compiled pass is absent ({kernel_aot.BUILD_COMMAND} builds it; make setup runs it)",
)


@pytest.fixture
def build() -> Iterator[None]:
    """Tests switch the process's kernel build: put back the one it had."""
    before = window.kernel_build("auto")
    yield
    window.kernel_build(before)


def test_the_build_is_of_this_source() -> None:
    k = kernel_aot.load()
    assert not isinstance(k, str), f"the AOT build is not used: {k}"
    assert k.kind == "aot"


_PLAN = """
import json, sys
import numpy as np
from planner_core import IterativeOptions
from planner_core.iterative import plan_iterative
from planner_core.window import kernel_kind, stack_rows, jet_scales
from planner_core.jets import ProblemCache
from tests.planner.test_window import _problem
p = _problem(7, 80)
res = plan_iterative(p, IterativeOptions(compiled=True))
cache = ProblemCache(p)
rows = stack_rows(cache, jet_scales(cache.durations))  # the global QP's rows: fill_rows
print(json.dumps({"kind": kernel_kind(), "ok": res.ok, "steps": res.stats["n_compiled_steps"],
                  "step_s": res.stats["step_time_median"],
                  "rows": int(rows[3].shape[0]),
                  "loaded": [m for m in ("numba", "llvmlite", "planner_core.window_kernel") if m in sys.modules]}))
"""


def test_a_plan_on_the_aot_build_never_imports_numba() -> None:
    r = subprocess.run([sys.executable, "-c", _PLAN], cwd=ROOT, capture_output=True, text=True, timeout=120,
                       check=True, env={"PATH": "/usr/bin:/bin", "PYTHONPATH": str(ROOT)})
    out = json.loads(r.stdout.strip().splitlines()[-1])
    assert out["kind"] == "aot" and out["ok"] and out["steps"] > 0 and out["rows"] > 0
    assert 0.0 < out["step_s"] < 0.05  # the steps' times, read from libc's clock by the pass itself
    assert out["loaded"] == [], f"loaded {out['loaded']} with the AOT build"


def _plan(build: str, seed: int, m: int) -> tuple[np.ndarray, dict[str, object]]:
    window.kernel_build(build)
    assert window.kernel_kind() == build, window.aot_unavailable()
    res = plan_iterative(_problem(seed, m), IterativeOptions(compiled=True))
    assert res.ok and res.trajectory is not None
    return res.trajectory.control_points, res.stats


@pytest.mark.parametrize(("seed", "m"), [(1, 40), (7, 150), (11, 400)])
def test_aot_plans_equal_jit_plans_bit_for_bit(build: None, seed: int, m: int) -> None:
    """Same source, same numba pipeline, same flags: the same arithmetic to the last bit."""
    aot, s_aot = _plan("aot", seed, m)
    jit, s_jit = _plan("jit", seed, m)
    np.testing.assert_array_equal(aot, jit)
    assert s_aot["n_compiled_steps"] == s_jit["n_compiled_steps"] and s_aot["n_compiled_steps"] > 0
    assert s_aot["recoveries"] == s_jit["recoveries"]


def test_aot_rows_equal_jit_rows_bit_for_bit(build: None) -> None:
    """`fill_rows` (the numpy window path's and the global QP's rows), with working limits."""
    problem = _problem(3, 30)
    cache = ProblemCache(problem)
    stores = {}
    for b in ("aot", "jit"):
        window.kernel_build(b)
        assert window.kernel_kind() == b
        store = window._RowStore(cache, jet_scales(cache.durations), span=4, working=True)
        store.hold(0, problem.m - 2)
        stores[b] = store
    for name in ("ab", "c0", "lim", "limw"):
        np.testing.assert_array_equal(getattr(stores["aot"], name), getattr(stores["jit"], name))


def test_a_stale_build_is_refused_with_the_reason(build: None, tmp_path: Path,
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """An edit of any file of the kernel after the build (here `window_factor.py`, which the
    exported functions only call): the AOT module is refused (its digest is not the sources'),
    the JIT compiles the sources as they are; asked for the AOT build only, none."""
    edited = tmp_path / "window_factor.py"
    sources = tuple(edited if p.name == edited.name else p for p in kernel_aot.SOURCES)
    assert sources != kernel_aot.SOURCES
    edited.write_text((kernel_aot.SOURCES[1].parent / edited.name).read_text() + "\n# an edit after the build\n")
    why = kernel_aot.load(sources)
    assert isinstance(why, str) and why.startswith("stale:") and kernel_aot.BUILD_COMMAND in why
    assert not isinstance(kernel_aot.load(), str)  # the build itself is of the sources as they are
    monkeypatch.setattr(kernel_aot, "SOURCES", sources)
    window.kernel_build("auto")
    assert window.kernel_kind() == "jit"
    reason = window.aot_unavailable()
    assert reason is not None and reason.startswith("stale:")
    window.kernel_build("aot")
    unavailable = window.kernel_unavailable()
    assert unavailable is not None and "stale:" in unavailable
    assert plan_iterative(_problem(1, 12)).ok  # on the numpy + daqp path


def test_use_compiled_kernel_false_still_means_no_compiled_pass(build: None) -> None:
    before = window.use_compiled_kernel(False, "test: off")
    try:
        assert window.kernel_kind() is None and window.kernel_unavailable() == "test: off"
        assert window.aot_unavailable() == "test: off"
    finally:
        window.use_compiled_kernel(before is None, before or "")


def test_arguments_are_checked_before_the_unchecked_unboxing() -> None:
    """pycc unboxes an array by its item size alone: a wrong dtype or an output that is not
    C-contiguous must be refused before the call, an input not laid out as declared copied."""
    k = kernel_aot.load()
    assert not isinstance(k, str), k
    problem = _problem(3, 8)
    cache = ProblemCache(problem)
    store = window._RowStore(cache, jet_scales(cache.durations), working=True)
    bs = cache.bound_spec
    args = [np.arange(problem.m - 1, dtype=np.int64), store._off, cache.hull, problem.waypoints, store.cs,
            bs.point, bs.code, bs.direction, int(bs.n_start), store._blim, store._face_off, store._pa, store._pb,
            window.INF, window.MARGIN, store.ab, store.c0, store.lim, store.limw, window.ADD_TOL]
    k.fill_rows(*args)
    ab = store.ab.copy()
    bad = list(args)
    bad[0] = bad[0].astype(np.float64)  # same item size, another dtype
    with pytest.raises(TypeError, match="segs"):
        k.fill_rows(*bad)
    bad = list(args)
    bad[15] = np.asfortranarray(store.ab)
    with pytest.raises(TypeError, match="ab"):
        k.fill_rows(*bad)
    bad = list(args)
    bad[4] = np.asfortranarray(store.cs)  # an input: copied, same values
    k.fill_rows(*bad)
    np.testing.assert_array_equal(store.ab, ab)


def test_a_build_for_another_cpu_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    """The build targets the CPU it was built on (as numba's JIT does): elsewhere it could stop
    on an illegal instruction, so it is refused by its CPU digest (this machine's flags stood in
    for by others here)."""
    monkeypatch.setattr(kernel_aot, "cpu_digest", lambda: 12345)
    why = kernel_aot.load()
    assert isinstance(why, str) and "another CPU" in why and kernel_aot.BUILD_COMMAND in why
