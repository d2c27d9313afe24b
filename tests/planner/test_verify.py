"""verify() catches an injected violation of each kind and names where it is."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from planner_core import Bounds, Polytope, Problem, Trajectory, plan, verify
from planner_core.bezier import bernstein_basis, hodographs, stacked_pieces
from planner_core.constraints import HULL_PIECES
from planner_core.formats.io import load_scenario

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


@pytest.fixture(scope="module")
def planned() -> tuple[Trajectory, Problem]:
    problem = load_scenario(json.loads((EXAMPLES / "scenario1.json").read_text())).problem
    res = plan(problem, "iterative")
    assert res.ok and res.trajectory is not None
    return res.trajectory, problem


def _with_ctrl(traj: Trajectory, ctrl: np.ndarray) -> Trajectory:
    return replace(traj, control_points=ctrl)


def test_clean_plan_passes(planned: tuple[Trajectory, Problem]) -> None:
    traj, problem = planned
    rep = verify(traj, problem)
    assert rep.ok, rep.summary()
    assert rep.summary().startswith("verify: OK")
    d = rep.to_dict()
    assert d["ok"] is True and d["failures"] == []
    json.dumps(d)  # serialisable


def test_waypoint_violation(planned: tuple[Trajectory, Problem]) -> None:
    traj, problem = planned
    ctrl = traj.control_points.copy()
    ctrl[2, 0] += [0.0, 1e-6, 0.0]  # start of segment 2 (waypoint 2)
    ctrl[1, -1] += [0.0, 1e-6, 0.0]
    rep = verify(_with_ctrl(traj, ctrl), problem)
    assert not rep.ok
    assert rep.waypoint_error.value == pytest.approx(1e-6, rel=1e-3)
    assert rep.waypoint_error.segment == 2
    assert "waypoint_error" in rep.summary()


def test_continuity_violation(planned: tuple[Trajectory, Problem]) -> None:
    traj, problem = planned
    ctrl = traj.control_points.copy()
    ctrl[3, 2] += [1e-3, 0.0, 0.0]  # P^2 of segment 3: acceleration jumps at waypoint 3
    rep = verify(_with_ctrl(traj, ctrl), problem)
    assert not rep.ok
    assert rep.continuity_error.value > 1e-6
    assert rep.continuity_error.segment == 3
    assert rep.continuity_error.order in (2, 3, 4)  # P^2 moves orders 2..4, not 0..1
    assert rep.waypoint_error.value == 0.0


def _hull_max(traj: Trajectory, k: int) -> float:
    """Largest certified value of order k: the hodographs' HULL_PIECES de Casteljau pieces."""
    pts = hodographs(traj.control_points, k, np.diff(traj.times))
    return float(np.abs(stacked_pieces(9 - k, HULL_PIECES) @ pts).max())


def _sample_max(traj: Trajectory, k: int) -> float:
    t = np.linspace(traj.t0, traj.t_end, 20001)
    return float(np.abs(traj.evaluate(t, k)).max())


@pytest.mark.parametrize("k", [1, 2, 3, 4])
def test_bound_violation_by_hull(planned: tuple[Trajectory, Problem], k: int) -> None:
    traj, problem = planned
    hi = problem.bounds.hi.copy()
    lo = problem.bounds.lo.copy()
    hi[k - 1] = _hull_max(traj, k) - 1e-4
    lo[k - 1] = -hi[k - 1]
    rep = verify(traj, replace(problem, bounds=Bounds(lo, hi)))
    assert not rep.ok
    assert rep.bound_violation_hull.value == pytest.approx(1e-4, rel=1e-3)
    assert rep.bound_violation_hull.order == k


@pytest.mark.parametrize("k", [1, 4])
def test_bound_violation_by_samples(planned: tuple[Trajectory, Problem], k: int) -> None:
    traj, problem = planned
    hi = problem.bounds.hi.copy()
    hi[k - 1] = 0.9 * _sample_max(traj, k)
    rep = verify(traj, replace(problem, bounds=Bounds(-hi, hi)))
    assert not rep.ok
    assert rep.bound_violation_sampled.value > 0.05 * hi[k - 1, 0]
    assert rep.bound_violation_sampled.order == k
    assert rep.bound_violation_sampled.time is not None


def test_corridor_violation(planned: tuple[Trajectory, Problem]) -> None:
    traj, problem = planned
    s = 4
    pts = bernstein_basis(9, np.linspace(0, 1, 500)) @ traj.control_points[s]
    # a plane that cuts the middle of segment 4's curve (keeps both waypoints inside)
    w0, w1 = traj.control_points[s, 0], traj.control_points[s, -1]
    chord = (w1 - w0) / np.linalg.norm(w1 - w0)
    dev = (pts - w0) - np.outer((pts - w0) @ chord, chord)
    normal = dev[int(np.argmax(np.linalg.norm(dev, axis=1)))]
    normal /= np.linalg.norm(normal)
    top = float((pts @ normal).max())
    ends = float(max(traj.control_points[s, 0] @ normal, traj.control_points[s, -1] @ normal))
    assert top > ends + 1e-3
    cut = Polytope(normal[None, :], np.array([0.5 * (top + ends)]))
    cors = list(problem.corridors or [None] * (problem.m - 1))
    cors[s] = cut
    rep = verify(traj, replace(problem, corridors=tuple(cors)))
    assert not rep.ok
    assert rep.corridor_violation_hull.segment == s
    assert rep.corridor_violation_sampled.segment == s
    assert rep.corridor_violation_sampled.value > 0


def test_structure_mismatch(planned: tuple[Trajectory, Problem]) -> None:
    traj, problem = planned
    shifted = replace(traj, times=traj.times + 0.5)
    rep = verify(shifted, problem)
    assert not rep.ok and "times" in rep.structure_error
    short = replace(traj, control_points=traj.control_points[:-1], times=traj.times[:-1])
    assert not verify(short, problem).ok


def test_boundary_jet_violation(planned: tuple[Trajectory, Problem]) -> None:
    traj, problem = planned
    init = problem.initial.copy()
    init[1] = [0.5, 0.0, 0.0]  # the plan starts at rest; claim it should start moving
    rep = verify(traj, replace(problem, initial=init))
    assert not rep.ok
    assert rep.boundary_error.value == pytest.approx(0.5)
    assert rep.boundary_error.order == 1


@pytest.mark.parametrize("offset", [30.0, 300.0, 3000.0, 30000.0])
@pytest.mark.parametrize("last", [0.2, 0.4])
def test_a_plan_far_from_the_origin_ending_on_a_short_segment_verifies(offset: float, last: float) -> None:
    """The final snap of a plan is a 4th difference of stored control points over d^4: far from
    the origin it carries rounding that an absolute tolerance refused (a 1000-waypoint mission in
    the service, 30 m out, last segment 0.45 s: boundary error 6e-7 in snap, refused). The check
    is net of that floor, as the junctions' is; a real boundary error is still caught."""
    bounds = Bounds.symmetric(10.0, 30.0, 500.0, 1e5)
    wps = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.0], [1.05, 0.52, 0.01]]) + offset
    problem = Problem.from_waypoints(wps, [1.5, last], bounds)
    res = plan(problem, recover=False)
    assert res.ok and res.trajectory is not None, res.message
    rep = verify(res.trajectory, problem)
    assert rep.ok, rep.summary()
    ctrl = res.trajectory.control_points.copy()
    ctrl[-1, -2, 0] += 1e-6 * (1.0 + offset * 1e-3)  # the last jet's velocity .. snap moved
    bad = verify(replace(res.trajectory, control_points=ctrl), problem)
    assert not bad.ok and bad.boundary_error.segment == problem.m - 2, bad.summary()
