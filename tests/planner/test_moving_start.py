"""A mission sent in flight starts from the vehicle's jet: a long first leg that starts by
accelerating away from its end cannot be certified as one degree-9 segment at any duration
(the velocity hodograph's control points run ahead of the bound), and the knot rule kept knots
off legs with a fast end. The fastest allocation then knots the first leg and plans it (a
lawn-mower mission in flight was refused so: tests/mock/test_missions_in_flight.py)."""

from __future__ import annotations

import numpy as np
import pytest

from planner_core import Bounds, Problem, fastest_durations, plan, rest_jet, verify

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
