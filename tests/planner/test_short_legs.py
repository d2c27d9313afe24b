"""Short legs (issue 25, point 4): the stop-to-stop profile that shapes a knotted leg's pieces is the
time-optimal jerk-limited one, and a 5 m diagonal rest-to-rest leg flies within 1.25x of it on its
binding axis (the time ruckig gives), verified and within every bound when sampled densely."""

from __future__ import annotations

import math

import numpy as np
import pytest

from planner_core import Bounds, Problem, allocate_times, fastest_durations, verify
from planner_core.timing import stop_to_stop_crossings

V, A, J = 3.0, 3.0, 10.0
DEFAULTS = Bounds.symmetric(V, A, J, 50.0)  # companion/config.py [planner.bounds]
NO_SNAP = 1e12  # the profile's stand-in for an absent bound


def s_curve_time(length: float, v: float = V, a: float = A, j: float = J) -> float:
    """The time-optimal rest-to-rest time under v, a, j in closed form, by regime."""
    if length >= v * (v / a + a / j) and v * j >= a * a:  # reaches a and v
        return length / v + v / a + a / j
    vp = (-(a / j) + math.sqrt((a / j) ** 2 + 4.0 * length / a)) / 2.0 * a
    if vp >= a * a / j:  # reaches a, not v
        return 2.0 * (vp / a + a / j)
    return 4.0 * (length / (2.0 * j)) ** (1.0 / 3.0)  # reaches neither: four jerk phases


@pytest.mark.parametrize("length", [0.2, 1.0, 3.0, 5.0, 20.0, 50.0])
def test_profile_is_the_time_optimal_s_curve(length: float) -> None:
    f = np.linspace(0.0, 1.0, 9)
    t = stop_to_stop_crossings(np.array([length]), np.array([[V, A, J, NO_SNAP]]), f)[0]
    assert t[0] == 0.0
    assert t[-1] == pytest.approx(s_curve_time(length), rel=1e-9)
    assert np.all(np.diff(t) > 0.0)
    assert np.allclose(t + t[::-1], t[-1], atol=1e-3 * t[-1])  # symmetric: decelerating mirrors accelerating


def test_snap_folds_into_a_slower_jerk() -> None:
    t_free = stop_to_stop_crossings(np.array([5.0]), np.array([[V, A, J, NO_SNAP]]), np.array([1.0]))[0, 0]
    t_snap = stop_to_stop_crossings(np.array([5.0]), np.array([[V, A, J, 50.0]]), np.array([1.0]))[0, 0]
    # j_eff = a / (a/j + j/s) = 6 at a 3, j 10, s 50: the S-curve at jerk 6
    assert t_snap == pytest.approx(s_curve_time(5.0, j=A / (A / J + J / 50.0)), rel=1e-9)
    assert t_snap > t_free


@pytest.mark.parametrize("direction", [(1.0, 1.0, 0.0), (1.0, 1.0, 1.0), (1.0, 0.0, 0.0)], ids=["xy", "xyz", "x"])
def test_five_metre_leg_within_a_quarter_of_the_binding_axis_optimum(direction: tuple[float, float, float]) -> None:
    u = np.asarray(direction) / np.linalg.norm(direction)
    wps = np.stack([np.zeros(3), 5.0 * u])
    problem = Problem.from_waypoints(wps, np.diff(allocate_times(wps, DEFAULTS)), DEFAULTS)
    fast = fastest_durations(problem)
    assert fast.ok and fast.result.trajectory is not None
    traj = fast.result.trajectory
    assert verify(traj, fast.problem).ok
    samples = np.linspace(traj.t0, traj.t_end, 20001)
    for k in range(1, 5):
        assert np.max(np.abs(traj.evaluate(samples, k))) <= DEFAULTS.hi[k - 1, 0] * (1.0 + 1e-9)
    assert np.allclose(traj.waypoints[fast.waypoint_index], wps, atol=1e-9)
    binding = s_curve_time(float(np.max(np.abs(wps[1]))))  # every axis has the same bounds
    assert traj.t_end - traj.t0 <= 1.25 * binding
