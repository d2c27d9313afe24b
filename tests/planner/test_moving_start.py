"""A mission sent in flight starts from the vehicle's jet: a long first leg that starts by
accelerating away from its end cannot be certified as one degree-9 segment at any duration
(the velocity hodograph's control points run ahead of the bound), and the knot rule kept knots
off legs with a fast end. The fastest allocation then knots the first leg and plans it (a
lawn-mower mission in flight was refused so: tests/mock/test_missions_in_flight.py)."""

from __future__ import annotations

import numpy as np
import pytest

from planner_core import (
    Bounds,
    Problem,
    Trajectory,
    allocate_times,
    build_corridors,
    fastest_durations,
    plan,
    plan_mission,
    rest_jet,
    verify,
)
from planner_core.bezier import segment_from_jets
from planner_core.missions import LEAD_TIMES, MissionPlan, lead_in

BOUNDS = Bounds.symmetric(2.4, 2.4, 8.0, 40.0)  # the companion's bounds within its 0.2 reserve


def _start(accel: list[float]) -> Problem:
    jet = rest_jet(np.array([5.12, 1.99, -2.0]))
    jet[1], jet[2] = [0.15, 1.43, -0.13], accel
    return Problem.from_waypoints(np.vstack([jet[0], [-4.9, 1.0, -2.0], [-4.9, 3.0, -2.0]]), [5.0, 2.0], BOUNDS,
                                  None, jet)


def test_one_segment_cannot_certify_the_leg_at_any_duration() -> None:
    """The premise: the first leg alone, unknotted, does not plan at any duration tried."""
    p = _start([1.17, 1.06, 0.65])
    for d in (3.0, 6.0, 10.0, 15.0, 25.0, 40.0):
        one = Problem.from_waypoints(p.waypoints[:2], [d], BOUNDS, None, p.initial)
        assert not plan(one, recover=False, diagnose=False).ok, d


@pytest.mark.parametrize("accel", [[1.17, 1.06, 0.65], [1.17, 0.0, 0.0], [0.8, -0.5, 0.2]])
def test_a_moving_start_plans_and_is_knotted_only_when_nothing_else_plans(accel: list[float]) -> None:
    p = _start(accel)
    a = fastest_durations(p)
    assert a.ok and a.result.trajectory is not None, a.result.message
    assert verify(a.result.trajectory, a.problem).ok
    # knots between the start and the first waypoint only where the plain search found nothing
    assert (a.waypoint_index[1] > 1) == (accel == [1.17, 1.06, 0.65]), a.waypoint_index
    np.testing.assert_allclose(a.result.trajectory.jet(a.result.trajectory.t0)[:3], p.initial[:3], atol=1e-6)
    assert np.linalg.norm(a.problem.waypoints[a.waypoint_index[-1]] - p.waypoints[-1]) < 1e-12


def test_a_start_that_plans_without_knots_keeps_its_plan() -> None:
    """Only a start that plans no other way is knotted: a gentle one is planned as before."""
    p = _start([0.0, 0.0, 0.0])
    a = fastest_durations(p)
    b = fastest_durations(p, first_leg_knots=False)
    assert a.ok and np.array_equal(a.durations, b.durations)


# -- durations fixed before planning (a timed mission, the companion's anytime start) --------


def _lawn(n: int, phase: float) -> np.ndarray:
    k = np.arange(n)
    row, col = k // 8, k % 8
    col = np.where(row % 2 == 1, 7 - col, col)
    return np.stack([2.0 * col - 7.0 + phase, 2.0 * row + 1.0, np.full(n, -2.0)], axis=1)


FULL = BOUNDS.scaled(1.0 / 0.8)  # a timed mission is planned within the full bounds, no reserve
MAP = (np.array([-100.4, -100.4, -50.4]), np.array([100.4, 100.4, 0.9]))  # the companion default map


def _timed_from(jet: np.ndarray, wps: np.ndarray, legs: float) -> MissionPlan:
    points = np.vstack([jet[0], wps])
    cors = build_corridors(points, [], MAP, 0.7)
    # the leg to waypoint 0 has no duration given: the companion allocates it from the velocity
    lead = np.diff(allocate_times(points[:2], FULL, initial_velocity=jet[1]))
    return plan_mission(points, FULL, cors, np.concatenate([lead, np.full(len(wps) - 1, legs)]), initial=jet)


@pytest.fixture(scope="module")
def flown() -> Trajectory:
    """A fast lawn-mower plan within the reserve, as the companion plans one: its jets are what a
    mission sent in flight starts from."""
    wps = _lawn(20, 2.8)
    mp = plan_mission(wps, BOUNDS, build_corridors(wps, [], MAP, 0.7))
    assert mp.ok and mp.trajectory is not None, mp.message
    return mp.trajectory


def test_timed_missions_sent_in_flight_plan_from_every_jet_of_a_fast_flight(
        flown: Trajectory, monkeypatch: pytest.MonkeyPatch) -> None:
    """A timed 5-waypoint mission sent at 40 instants of a fast flight plans from each, starting
    with the flown jet exactly, the knot on the vehicle's own motion and never a given waypoint;
    without the lead knot a share of them is refused (one segment from a fast or jerky jet breaks
    the corridor or the acceleration bound at every duration: 1 in 3 did in the companion)."""
    wps = _lawn(5, 3.5)
    ts = np.linspace(flown.t0 + 0.5, flown.t_end - 1.0, 40)
    for t in ts:
        jet = flown.jet(float(t))
        mp = _timed_from(jet, wps, 2.0)
        assert mp.ok and mp.trajectory is not None, (t, mp.message)
        assert verify(mp.trajectory, mp.problem).ok
        np.testing.assert_allclose(mp.trajectory.jet(mp.trajectory.t0), jet, atol=1e-6)
        np.testing.assert_allclose(mp.problem.waypoints[mp.waypoint_index], np.vstack([jet[0], wps]), atol=1e-12)
        if mp.problem.m > len(wps) + 1:  # the lead knot: tau s along the flown jet's own curve
            assert mp.waypoint_index[1] == 2
            tau = float(mp.problem.times[1] - mp.problem.times[0])
            assert tau in LEAD_TIMES
            lead = lead_in(jet, FULL, mp.problem.corridors[0] if mp.problem.corridors else None)
            assert lead is not None and np.allclose(lead[1][0], mp.problem.waypoints[1])
    monkeypatch.setattr("planner_core.missions.LEAD_TIMES", ())
    refused = sum(not _timed_from(flown.jet(float(t)), wps, 2.0).ok for t in ts)
    assert refused >= 5, refused


def test_the_lead_is_the_jets_own_curve_and_holds_the_bounds() -> None:
    """lead_in's segment is the Taylor curve of the jet (its end jet by the series) certified
    within the bounds; a jet beyond the bounds has no lead."""
    rng = np.random.default_rng(7)
    for _ in range(200):
        jet = rest_jet(rng.uniform(-3, 3, 3))
        jet[1:] = rng.uniform(-1, 1, (4, 3)) * np.array([[2.0], [2.0], [6.0], [30.0]])
        lead = lead_in(jet, BOUNDS, None)
        if lead is None:
            continue
        tau, end = lead
        ctrl = segment_from_jets(jet, end, tau)
        seg = Trajectory(np.array([0.0, tau]), ctrl[None], None, {})
        for u in (0.25, 0.5, 1.0):
            t = u * tau
            series = sum(jet[i] * t**i / np.prod(np.arange(1, i + 1)) for i in range(5))
            np.testing.assert_allclose(seg.jet(t)[0], series, atol=1e-9)
    fast = rest_jet(np.zeros(3))
    fast[1] = [2.6, 0.0, 0.0]  # above the 2.4 m/s bound: no lead can hold it
    assert lead_in(fast, BOUNDS, None) is None
