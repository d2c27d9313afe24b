"""Plan quality on random cluttered scenes (benchmarks/quality.py): iterative vs the global optimum."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

from planner_core import Trajectory, verify
from planner_core.bezier import bernstein_basis
from planner_core.global_qp import plan_global
from planner_core.iterative import plan_iterative

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "benchmarks"))

from minsnap_compare import power_to_bezier
from quality import faster, random_scenario, snap_cost


def _simpson_snap(traj: Trajectory, n: int = 400) -> float:
    """∫|snap|^2 dt by composite Simpson per segment (snap may jump at junctions of a random curve)."""
    total = 0.0
    w = np.ones(n + 1)
    w[1:-1:2], w[2:-1:2] = 4.0, 2.0
    for t0, t1 in zip(traj.times[:-1], traj.times[1:], strict=True):
        # stay strictly inside the segment so evaluation never picks the neighbour at a junction
        eps = 1e-12 * (t1 - t0)
        t = np.linspace(t0 + eps, t1 - eps, n + 1)
        f = np.sum(traj.evaluate(t, 4) ** 2, axis=1)
        total += float(w @ f) * (t[1] - t[0]) / 3.0
    return total


def test_snap_cost_matches_numeric_integration() -> None:
    rng = np.random.default_rng(3)
    ctrl = rng.normal(size=(4, 10, 3)) * 3.0
    times = np.concatenate([[0.5], 0.5 + np.cumsum(rng.uniform(0.3, 4.0, 4))])  # unequal: tests Δ scaling
    traj = Trajectory(times, ctrl)
    exact = snap_cost(traj)
    assert exact > 0.0
    assert abs(exact - _simpson_snap(traj)) <= 1e-6 * exact


def test_snap_cost_of_a_planned_trajectory_matches_numeric_integration() -> None:
    res = plan_global(random_scenario(1).problem)
    assert res.ok and res.trajectory is not None
    exact = snap_cost(res.trajectory)
    assert abs(exact - _simpson_snap(res.trajectory)) <= 1e-6 * exact
    assert exact == pytest.approx(res.stats["integrated_snap"], rel=1e-12)


def test_power_to_bezier_is_an_exact_change_of_basis() -> None:
    rng = np.random.default_rng(5)
    coeffs = rng.normal(size=(3, 10, 3))
    durations = np.array([0.7, 2.0, 3.5])
    ctrl = power_to_bezier(coeffs, durations)
    for s in range(3):
        tau = np.linspace(0.0, durations[s], 50)
        power = (tau[:, None] ** np.arange(10)) @ coeffs[s]
        bez = bernstein_basis(9, tau / durations[s]) @ ctrl[s]
        assert np.allclose(power, bez, rtol=1e-10, atol=1e-10 * np.abs(power).max())


def test_iterative_succeeds_where_global_does_and_never_beats_it() -> None:
    scenes = [random_scenario(s) for s in range(4)] + [faster(random_scenario(4), 0.7)]
    solved = compared = 0
    for sc in scenes:
        g = plan_global(sc.problem)
        if not g.ok:
            continue
        solved += 1
        assert g.trajectory is not None and verify(g.trajectory, sc.problem).ok
        it = plan_iterative(sc.problem)
        assert it.ok, f"{sc.name}: iterative failed where global succeeded: {it.message}"
        assert it.trajectory is not None
        if not np.array_equal(it.trajectory.times, sc.problem.times):
            continue  # recovery stretched durations: a different problem, not comparable
        compared += 1
        assert verify(it.trajectory, sc.problem).ok
        gc, ic = snap_cost(g.trajectory), snap_cost(it.trajectory)
        # the global QP is optimal over the same constraints; both are solved to ~1e-9
        assert ic >= gc * (1.0 - 1e-6), f"{sc.name}: iterative {ic} below the global optimum {gc}"
    assert solved >= 3 and compared >= solved - 1
