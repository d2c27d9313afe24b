"""Iterative and global planners: verified, continuous, inside bounds and corridors, costs ordered."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from planner_core import Bounds, IterativeOptions, PlanStatus, Polytope, Problem, plan, verify
from planner_core.constraints import integrated_cost
from planner_core.formats.io import load_scenario
from planner_core.jets import initial_jets, solve_jets
from planner_core.qp import QPStatus

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def box_corridor(p0: np.ndarray, p1: np.ndarray, pad: float) -> Polytope:
    lo = np.minimum(p0, p1) - pad
    hi = np.maximum(p0, p1) + pad
    eye = np.eye(3)
    return Polytope(np.concatenate([eye, -eye]), np.concatenate([hi, -lo]))


def random_problem(seed: int, m: int, corridors: bool = True) -> Problem:
    """Feasible by construction: moderate spacing, generous durations, padded box corridors."""
    rng = np.random.default_rng(seed)
    steps = rng.normal(size=(m - 1, 3))
    steps[:, 2] *= 0.3
    steps *= rng.uniform(2.0, 5.0, size=(m - 1, 1)) / np.linalg.norm(steps, axis=1, keepdims=True)
    wps = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
    durations = np.linalg.norm(steps, axis=1) / 2.0 + 2.0
    cors = tuple(box_corridor(wps[i], wps[i + 1], 1.0) for i in range(m - 1)) if corridors else None
    return Problem.from_waypoints(wps, durations, Bounds.symmetric(7, 6.5, 15, 60), cors)


def check_plan(problem: Problem, method: str, **opts: object) -> float:
    res = plan(problem, method, **opts)  # type: ignore[arg-type]
    assert res.status is PlanStatus.OK, res.message
    assert res.trajectory is not None
    rep = verify(res.trajectory, problem)
    assert rep.ok, rep.summary()
    assert rep.continuity_error.value <= 1e-6
    assert rep.bound_violation_sampled.value <= 0.0
    assert rep.corridor_violation_sampled.value <= 0.0
    assert rep.bound_violation_hull.value <= 1e-9
    return integrated_cost(res.trajectory.control_points, problem.durations, 4)


@settings(max_examples=8, deadline=None)
@given(st.integers(0, 10_000), st.integers(3, 8))
def test_random_feasible_scenarios(seed: int, m: int) -> None:
    problem = random_problem(seed, m)
    c_global = check_plan(problem, "global")
    for window in (1, 3):
        c_iter = check_plan(problem, "iterative", window=window)
        # the global optimum over the same feasible set is never worse
        assert c_global <= c_iter * (1 + 1e-6) + 1e-9


@pytest.mark.parametrize("name", ["scenario1.json", "scenario2.json"])
@pytest.mark.parametrize("method", ["iterative", "global"])
def test_examples_plan_and_verify(name: str, method: str) -> None:
    scenario = load_scenario(json.loads((EXAMPLES / name).read_text()))
    check_plan(scenario.problem, method)


@pytest.mark.parametrize("cost", ["snap", "jerk", "waypoint-snap"])
def test_costs_and_stats(cost: str) -> None:
    problem = random_problem(7, 6)
    res = plan(problem, "iterative", cost=cost, window=2)
    assert res.ok
    assert res.stats["cost"] == cost
    assert cost.split("-")[-1] in res.stats["cost_note"]
    if cost == "waypoint-snap":
        assert "regulariser" in res.stats["cost_note"]


def test_osqp_backend_matches_daqp() -> None:
    problem = random_problem(11, 6)
    a = plan(problem, "iterative", backend="daqp", window=2)
    b = plan(problem, "iterative", backend="osqp", window=2)
    assert a.ok and b.ok
    assert a.stats["integrated_snap"] == pytest.approx(b.stats["integrated_snap"], rel=1e-5)


def test_window_one_needs_recovery_or_succeeds_and_reports_it() -> None:
    problem = random_problem(3, 8)
    res = plan(problem, "iterative", window=1)
    assert res.ok
    assert isinstance(res.stats["recoveries"], list)


def test_solve_jets_keeps_fixed_jets_bit_for_bit() -> None:
    problem = random_problem(5, 7)
    base = plan(problem, "global")
    assert base.ok and base.trajectory is not None
    from planner_core.bezier import start_jet

    d = problem.durations
    jets = np.stack([start_jet(base.trajectory.control_points[i], d[i]) for i in range(problem.m - 1)]
                    + [problem.final])
    jets[:, 0] = problem.waypoints
    moved = problem.waypoints.copy()
    moved[3] += np.array([0.3, -0.2, 0.1])
    from dataclasses import replace

    p2 = replace(problem, waypoints=moved)
    jets2 = jets.copy()
    jets2[3, 0] = moved[3]
    res = solve_jets(p2, jets2, [2, 3, 4])
    assert res.status is QPStatus.OPTIMAL
    untouched = [0, 1, 5, 6]
    assert np.array_equal(res.jets[untouched], jets2[untouched])
    assert res.max_violation <= 1e-9


def test_solve_jets_rejects_non_interior() -> None:
    problem = random_problem(5, 5)
    with pytest.raises(ValueError, match="free"):
        solve_jets(problem, initial_jets(problem), [0])


def test_global_jerk_cost_option() -> None:
    problem = random_problem(9, 5)
    snap = plan(problem, "global", cost="snap")
    jerk = plan(problem, "global", cost="jerk")
    assert snap.ok and jerk.ok
    # each optimum is best for its own cost
    assert snap.stats["integrated_snap"] <= jerk.stats["integrated_snap"] * (1 + 1e-6)
    assert jerk.stats["integrated_jerk"] <= snap.stats["integrated_jerk"] * (1 + 1e-6)


def test_invalid_options() -> None:
    with pytest.raises(ValueError, match="window"):
        IterativeOptions(window=0)
    with pytest.raises(ValueError, match="method"):
        plan(random_problem(1, 4), "nope")


def test_row_blocks_match_bezier_hull() -> None:
    """Every cached row equals the hull quantity computed from the segment's control points."""
    from planner_core.bezier import hodograph, segment_from_jets, stacked_pieces
    from planner_core.constraints import HULL_PIECES, KIND_BOUND
    from planner_core.jets import ProblemCache

    problem = random_problem(13, 5)
    cache = ProblemCache(problem)
    rng = np.random.default_rng(0)
    jets = rng.normal(size=(5, 5, 3))
    jets[:, 0] = problem.waypoints
    d = problem.durations
    for s in range(4):
        blk = cache.blocks(s)
        val = blk.c0 + blk.A @ jets[s, 1:].ravel() + blk.B @ jets[s + 1, 1:].ravel()
        ctrl = segment_from_jets(jets[s], jets[s + 1], d[s])
        hodo = {k: stacked_pieces(9 - k, HULL_PIECES) @ hodograph(ctrl, k, d[s]) for k in range(1, 5)}
        bound = blk.kind == KIND_BOUND
        # bound rows: the multiset of values equals the control points of the HULL_PIECES pieces
        # of every hodograph, orders 1..4
        expect = np.sort(np.concatenate([hodo[k].ravel() for k in range(1, 5)]))
        assert np.allclose(np.sort(val[bound]), expect, rtol=1e-12, atol=1e-9)
        poly = problem.corridor(s)
        assert poly is not None
        expect_c = np.sort((ctrl[1:9] @ poly.A.T).ravel())
        assert np.allclose(np.sort(val[~bound]), expect_c, rtol=1e-12, atol=1e-9)
        # the 'half' rows depend on the start jet only
        half = blk.role("half")
        assert not np.any(blk.B[half])
        assert not np.any(blk.A[blk.dead("a")])


def test_global_backends_agree() -> None:
    problem = random_problem(21, 7)
    a = plan(problem, "global", backend="osqp")
    b = plan(problem, "global", backend="daqp")
    assert a.ok and b.ok
    assert a.stats["integrated_snap"] == pytest.approx(b.stats["integrated_snap"], rel=1e-6)


def test_window_larger_than_problem_is_clipped() -> None:
    problem = random_problem(4, 4)
    res = plan(problem, "iterative", window=10)
    glob = plan(problem, "global")
    assert res.ok and glob.ok
    # one QP over all interior jets with the terminal jet fixed is the global problem
    assert res.stats["integrated_snap"] == pytest.approx(glob.stats["integrated_snap"], rel=1e-6)


def test_diagnosis_names_corridor_group() -> None:
    from dataclasses import replace

    from planner_core.result import PlanStatus as Status

    problem = random_problem(2, 5)
    init = problem.initial.copy()
    poly = problem.corridor(0)
    assert poly is not None
    # leave along the outward normal of one corridor face: P^1 = W0 + v Δ/9 lies outside
    face = int(np.argmin(poly.b - poly.A @ problem.waypoints[0]))
    room = float(poly.b[face] - poly.A[face] @ problem.waypoints[0])
    init[1] = poly.A[face] * (room + 0.5) * 9.0 / problem.durations[0]
    init[1] = np.clip(init[1], -6.9, 6.9)
    res = plan(replace(problem, initial=init), "iterative")
    assert res.status is Status.INFEASIBLE
    assert res.diagnosis is not None
    assert res.diagnosis.waypoint == 1 and res.diagnosis.segment == 0
    assert res.diagnosis.kind == "corridor"
    assert "corridor of segment 0" in res.message


def test_plan_is_deterministic_and_input_untouched() -> None:
    problem = random_problem(17, 6)
    before = problem.waypoints.copy()
    a = plan(problem)
    b = plan(problem)
    assert a.trajectory is not None and b.trajectory is not None
    assert np.array_equal(a.trajectory.control_points, b.trajectory.control_points)
    assert np.array_equal(problem.waypoints, before)


def test_global_rejects_iterative_options() -> None:
    with pytest.raises(ValueError, match="window"):
        plan(random_problem(1, 4), "global", window=3)
