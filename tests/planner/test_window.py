"""The iterative pass's fast path: same rows and same answers as the general jet solver."""

from __future__ import annotations

import numpy as np
import pytest

from planner_core import Bounds, IterativeOptions, Polytope, Problem, iterative, verify, window
from planner_core.iterative import plan_iterative
from planner_core.jets import NV, ProblemCache, initial_jets, solve_jets
from planner_core.window import WindowSolver, jet_scales


def _problem(seed: int, m: int) -> Problem:
    """Random walk; corridors with varying face counts (boxes, boxes plus a slanted face, none)."""
    rng = np.random.default_rng(seed)
    steps = rng.normal(size=(m - 1, 3))
    steps *= rng.uniform(2.0, 4.0, size=(m - 1, 1)) / np.linalg.norm(steps, axis=1, keepdims=True)
    wps = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
    cors: list[Polytope | None] = []
    eye = np.eye(3)
    for i in range(m - 1):
        lo = np.minimum(wps[i], wps[i + 1]) - 1.0
        hi = np.maximum(wps[i], wps[i + 1]) + 1.0
        A, b = np.concatenate([eye, -eye]), np.concatenate([hi, -lo])
        if i % 3 == 1:
            n = rng.normal(size=3)
            n /= np.linalg.norm(n)
            mid = 0.5 * (wps[i] + wps[i + 1])
            A, b = np.vstack([A, n]), np.append(b, n @ mid + 3.0)
        cors.append(None if i % 5 == 3 else Polytope(A, b))
    durations = np.linalg.norm(steps, axis=1) / 2.0 + 1.5
    return Problem.from_waypoints(wps, durations, Bounds.symmetric(7, 6.5, 15, 60), tuple(cors))


# (span, compiled): a store sliding 3 segments at a time (and re-sized for a window wider than
# that), and one holding the whole mission
@pytest.mark.parametrize(("span", "compiled"), [(3, True), (None, True), (3, False), (None, False)])
def test_stacked_rows_equal_segment_blocks(span: int | None, compiled: bool, monkeypatch: pytest.MonkeyPatch) -> None:
    if not compiled:  # as where numba cannot run: the numpy fill
        monkeypatch.setattr(window, "_kernel_or_reason", lambda: "no JIT here")
    problem = _problem(3, 12)
    cache = ProblemCache(problem)
    cs = jet_scales(problem.durations)
    store = window._RowStore(cache, cs, span=span, working=True)
    # windows as the pass asks for them (segments j-1 .. j+2), one wider than the span, one going back
    asks = [(max(0, j - 1), min(j + 2, problem.m - 2)) for j in range(problem.m - 1)]
    asks[5] = (3, 8)
    asks.append((0, 1))
    for s0, s1 in asks:
        row0 = store.hold(s0, s1)
        assert store.seg0 <= s0 and s1 < store.seg1 and row0 == store.off[store.seg0]
        for s in range(s0, s1 + 1):
            blk = cache.blocks(s)
            rows = slice(store.off[s] - row0, store.off[s + 1] - row0)
            assert store.n1[s] == blk.n1 and store.n2[s] == blk.n2
            np.testing.assert_allclose(store.ab[rows, :NV], blk.A * cs[s], rtol=1e-13, atol=1e-12)
            np.testing.assert_allclose(store.ab[rows, NV:], blk.B * cs[s + 1], rtol=1e-13, atol=1e-12)
            np.testing.assert_allclose(store.c0[rows], blk.c0, rtol=1e-13, atol=1e-12)
            np.testing.assert_array_equal(store.lim[:, rows], blk.lim)
            np.testing.assert_array_equal(store.limw[:2, rows], blk.lim[:2])  # tightened, for the solver
            hi_t = blk.lim[1]
            assert np.all(store.limw[3, rows] >= hi_t)
            assert np.all(store.limw[3, rows] - hi_t <= 1e-11 * (1 + np.abs(hi_t)))
    if span is not None:  # it held a few segments' rows at a time, never the mission's
        assert store.c0.size < store.n_rows


def test_sliding_row_store_plans_as_one_holding_every_row(monkeypatch: pytest.MonkeyPatch) -> None:
    """The numpy window path with rows built a few segments at a time, slid forward and rebuilt
    after recoveries, solves the same windows as with every row of the mission held."""
    monkeypatch.setattr(window, "_kernel_or_reason", lambda: "no JIT here")
    problem = _problem(3, 14)  # window=1 needs recoveries here: solvers over pieces of the mission
    plans = {}
    for span in (2, 5, 10**6):
        monkeypatch.setattr(window, "CHUNK", span)
        for h in (1, 4):
            plans[span, h] = plan_iterative(problem, IterativeOptions(window=h, compiled=False))
    for h in (1, 4):
        ref = plans[10**6, h]
        assert ref.ok and ref.trajectory is not None
        for span in (2, 5):
            res = plans[span, h]
            assert res.ok and res.trajectory is not None
            def what(r: dict[str, object]) -> dict[str, object]:
                return {k: v for k, v in r.items() if k != "time"}

            assert [what(r) for r in res.stats["recoveries"]] == [what(r) for r in ref.stats["recoveries"]]
            np.testing.assert_allclose(res.trajectory.control_points, ref.trajectory.control_points,
                                       rtol=0.0, atol=1e-12)
    assert len(plans[10**6, 1].stats["recoveries"]) > 0


def test_compiled_pass_builds_the_stacked_rows() -> None:
    """The compiled pass builds rows where it needs them (`_materialize`) and checks a segment's rows
    from its control points (`_seg_check`): both must agree with the stacked rows."""
    if window.kernel_unavailable() is not None:
        pytest.skip(f"compiled pass unavailable: {window.kernel_unavailable()}")
    from planner_core import window_kernel as wk

    problem = _problem(3, 12)
    cache = ProblemCache(problem)
    fast = window._RowStore(cache, jet_scales(problem.durations), working=True)
    fast.hold(0, problem.m - 2)  # the numpy path's stacked rows, every segment's (row0 = 0)
    c = window._compact_rows(fast)
    rng = np.random.default_rng(0)
    pts = np.empty((cache.hull.shape[1] + 10, 3))  # the hull's points, then the segment's jets
    nz = wk.nonzero_runs(cache.hull)
    bad = np.empty(int(np.max(np.diff(fast.off))), dtype=np.int64)
    for s in range(problem.m - 1):
        n = fast.off[s + 1] - fast.off[s]
        rows = slice(fast.off[s], fast.off[s + 1])
        # every row of s built alone (both jets fixed at zero: constants only, no free column)
        ids = np.arange(n, dtype=np.int64)
        seg = np.full(n, s, dtype=np.int64)
        fixed = np.full(n, -1, dtype=np.int64)
        wab, nrm, lim4 = np.empty((n, 2 * NV)), np.empty(n), np.empty((4, n))
        wk.materialize(ids, n, fast.off[s], seg, fixed, fixed, c.off, cache.hull, fast.cs, c.pr, c.pd, c.bn1,
                        c.nb, c.face_off, c.pa, problem.waypoints, c.b6, c.f6, np.zeros(2 * NV), wab, nrm, lim4)
        np.testing.assert_array_equal(wab, fast.ab[rows])
        assert np.all(nrm == 0.0)
        np.testing.assert_array_equal(lim4[:2], fast.lim[:2, rows] - fast.c0[rows])
        np.testing.assert_array_equal(lim4[2:], fast.limw[2:, rows] - fast.c0[rows])
        # jets at random: the rows outside their limits are exactly those the stacked rows say
        for scale in (0.1, 3.0, 30.0):
            xa, xb = scale * rng.normal(size=(4, 3)), scale * rng.normal(size=(4, 3))
            x = np.concatenate([xa.ravel() / fast.cs[s], xb.ravel() / fast.cs[s + 1]])  # scaled unknowns
            vals = fast.c0[rows] + fast.ab[rows] @ x
            for lra, lrb in ((0, n), (fast.n1[s], n), (0, fast.n1[s]), (fast.n1[s] + fast.n2[s], n)):
                nbad = wk.seg_check(s, lra, lrb, xa, xb, 2, 3, 0.0, cache.hull, c.pr, c.pd, c.bn1, c.nb,
                                     c.face_off, c.pa, problem.waypoints, c.b6, c.f6, nz, pts, bad)
                lim = fast.lim[:, rows]
                out = (vals > lim[3]) | (vals < lim[2])
                # the two evaluations round differently: ignore rows within 1e-9 of a limit
                near = (np.abs(vals - lim[3]) < 1e-9) | (np.abs(vals - lim[2]) < 1e-9)
                want = {lr for lr in range(lra, lrb) if out[lr] and not near[lr]}
                got = set(bad[:nbad].tolist())
                assert want <= got and got - want <= {lr for lr in range(lra, lrb) if near[lr]}


@pytest.mark.parametrize("chunk", [2, 64])
def test_window_solve_matches_general_solver(chunk: int, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(window, "CHUNK", chunk)  # rows held a few segments at a time (2: fewer than a window)
    problem = _problem(5, 14)
    cache = ProblemCache(problem)
    fast = WindowSolver(cache)
    jets = initial_jets(problem)
    m = problem.m
    for j in range(1, m - 1):
        f1 = min(j + 3, m - 2)
        d = fast.solve(jets, j, f1, True)
        ref = solve_jets(problem, jets, list(range(j, f1 + 1)), open_end=True, cache=cache)
        assert (d is not None) == ref.ok
        assert d is not None  # this scene is feasible window by window
        np.testing.assert_allclose(d, ref.jets[j : f1 + 1, 1:], rtol=1e-6, atol=1e-6)
        jets[j, 1:] = d[0]


def test_fast_and_general_paths_plan_the_same_trajectory(monkeypatch: pytest.MonkeyPatch) -> None:
    problem = _problem(7, 10)
    opts = IterativeOptions()
    fast = plan_iterative(problem, opts)
    monkeypatch.setattr(iterative, "_fast_solver", lambda cache, opts: None)
    slow = plan_iterative(problem, opts)
    assert fast.ok and slow.ok and fast.trajectory is not None and slow.trajectory is not None
    np.testing.assert_allclose(fast.trajectory.control_points, slow.trajectory.control_points, atol=1e-6)


def test_global_sparse_path_is_the_exact_optimum() -> None:
    from planner_core import global_qp
    from planner_core.constraints import integrated_cost
    from planner_core.jets import trajectory_from_jets

    problem = _problem(11, 9)
    res = global_qp.plan_global(problem)
    assert res.ok and res.trajectory is not None
    assert res.stats["solved_by"].startswith("iterative warm start")
    ref = solve_jets(problem, initial_jets(problem), list(range(1, problem.m - 1)), backend="daqp")
    assert ref.ok
    c_ref = integrated_cost(trajectory_from_jets(problem, ref.jets).control_points, problem.durations, 4)
    assert abs(res.stats["integrated_snap"] - c_ref) <= 1e-7 * c_ref
    # the cold solve (the paper's baseline, for benchmarks) reaches the same optimum
    cold = global_qp.plan_global(problem, warm_start=False)
    assert cold.ok and cold.stats["solved_by"].startswith("osqp")
    assert abs(cold.stats["integrated_snap"] - c_ref) <= 1e-7 * c_ref
    # the OSQP fallback (no warm start) reaches the same optimum
    cache = ProblemCache(problem)
    qp = global_qp._GlobalQP(problem, cache, "snap")
    x = global_qp._osqp_refined(qp, None)
    assert x is not None and qp.violation(x) <= 1e-9
    np.testing.assert_allclose(x, ref.jets[1:-1, 1:].ravel(), rtol=1e-6, atol=1e-6)


@pytest.mark.parametrize(("seed", "h"), [(1, 2), (4, 4), (9, 6), (12, 3)])
def test_compiled_pass_matches_daqp_window_by_window(seed: int, h: int) -> None:
    """window_kernel (block-tridiagonal Goldfarb-Idnani) against WindowSolver.solve + daqp: the same
    QP per window, so the same committed jets, and every window settled by the compiled pass."""
    problem = _problem(seed, 24)
    comp = plan_iterative(problem, IterativeOptions(window=h))
    ref = plan_iterative(problem, IterativeOptions(window=h, compiled=False))
    assert comp.ok and ref.ok and comp.trajectory is not None and ref.trajectory is not None
    assert comp.stats["n_compiled_steps"] == problem.m - 2
    assert ref.stats["n_compiled_steps"] == 0
    scale = np.abs(ref.trajectory.control_points).max()
    np.testing.assert_allclose(comp.trajectory.control_points, ref.trajectory.control_points, atol=1e-8 * scale)
    rep = verify(comp.trajectory, problem)
    assert rep.ok, rep.summary()


def test_compiled_pass_hands_infeasible_windows_to_recovery() -> None:
    """The paper's one-jet window is infeasible at some waypoints of this scene: the compiled pass
    stops there, the general path recovers (backtrack/widen), and the pass resumes compiled."""
    problem = _problem(3, 14)
    res = plan_iterative(problem, IterativeOptions(window=1))
    assert res.ok and res.trajectory is not None
    n_rec = len(res.stats["recoveries"])
    assert n_rec > 0
    assert 0 < res.stats["n_compiled_steps"] < problem.m - 2
    # every waypoint is settled by exactly one of the two paths
    assert res.stats["n_compiled_steps"] + n_rec == problem.m - 2
    rep = verify(res.trajectory, problem)
    assert rep.ok, rep.summary()


def test_without_the_kernel_every_window_takes_the_daqp_path(monkeypatch: pytest.MonkeyPatch) -> None:
    """Where numba cannot run (a W^X memory policy refuses its JIT), the planner still plans the
    same verified trajectory, on the numpy + daqp path, and says why."""
    problem = _problem(4, 16)
    comp = plan_iterative(problem, IterativeOptions(window=4))
    monkeypatch.setattr(window, "_kernel_or_reason", lambda: "OSError: cannot allocate executable memory")
    slow = plan_iterative(problem, IterativeOptions(window=4))
    assert comp.ok and slow.ok and comp.trajectory is not None and slow.trajectory is not None
    assert comp.stats["compiled_unavailable"] is None and comp.stats["n_compiled_steps"] == problem.m - 2
    assert slow.stats["n_compiled_steps"] == 0
    assert "executable memory" in slow.stats["compiled_unavailable"]
    scale = np.abs(comp.trajectory.control_points).max()
    np.testing.assert_allclose(slow.trajectory.control_points, comp.trajectory.control_points, atol=1e-8 * scale)
    assert verify(slow.trajectory, problem).ok


def test_a_process_can_plan_without_ever_loading_numba() -> None:
    """The companion's service process plans small replans itself and leaves long plans to
    worker processes: with the kernel disabled it plans, and numba (~70 MB) is never imported."""
    import subprocess
    import sys

    code = (
        "import sys\n"
        "from planner_core import use_compiled_kernel\n"
        "use_compiled_kernel(False, 'service process')\n"
        "from planner_core.iterative import warm_up\n"
        "print(warm_up(), 'numba' in sys.modules, 'llvmlite' in sys.modules)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120, check=True)
    assert out.stdout.split() == ["service", "process", "False", "False"]
