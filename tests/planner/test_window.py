"""The iterative pass's fast path: same rows and same answers as the general jet solver."""

from __future__ import annotations

import numpy as np
import pytest

from planner_core import Bounds, IterativeOptions, Polytope, Problem, iterative, window
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


@pytest.mark.parametrize("chunk", [3, 64])
def test_stacked_rows_equal_segment_blocks(chunk: int, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(window, "CHUNK", chunk)
    problem = _problem(3, 12)
    cache = ProblemCache(problem)
    fast = WindowSolver(cache)
    fast._fill(0, (problem.m - 2) // chunk)
    cs = jet_scales(problem.durations)
    for s in range(problem.m - 1):
        blk = cache.blocks(s)
        rows = slice(fast.off[s], fast.off[s + 1])
        assert fast.n1[s] == blk.n1 and fast.n2[s] == blk.n2
        np.testing.assert_allclose(fast.ab[rows, :NV], blk.A * cs[s], rtol=1e-13, atol=1e-12)
        np.testing.assert_allclose(fast.ab[rows, NV:], blk.B * cs[s + 1], rtol=1e-13, atol=1e-12)
        np.testing.assert_allclose(fast.c0[rows], blk.c0, rtol=1e-13, atol=1e-12)
        np.testing.assert_array_equal(fast.lim[:, rows], blk.lim)


@pytest.mark.parametrize("chunk", [2, 64])
def test_window_solve_matches_general_solver(chunk: int, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(window, "CHUNK", chunk)  # rows filled lazily across chunk borders
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
    # the OSQP fallback (no warm start) reaches the same optimum
    cache = ProblemCache(problem)
    qp = global_qp._GlobalQP(problem, cache, "snap")
    x = global_qp._osqp_refined(qp, None)
    assert x is not None and qp.violation(x) <= 1e-9
    np.testing.assert_allclose(x, ref.jets[1:-1, 1:].ravel(), rtol=1e-6, atol=1e-6)
