"""planner_core.flight_time_lower_bound: a proven lower bound on the flight time through waypoints,
for any curve within the bounds (issue 12 measures its mission target against the weaker
per-segment bound, which this one contains)."""

from __future__ import annotations

import numpy as np
import pytest
import ruckig  # a test extra: the reference time-optimal jerk-limited solver
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from planner_core import (
    Bounds,
    Problem,
    fastest_durations,
    flight_time_lower_bound,
    plan,
    scaled_durations,
)
from planner_core.lower_bound import axis_runs, run_time


def _ruckig_time(d: float, a0: float, a1: float, v: float, a: float, j: float) -> float | None:
    inp = ruckig.InputParameter(1)
    inp.current_position, inp.target_position = [0.0], [d]
    inp.current_acceleration, inp.target_acceleration = [a0], [a1]
    inp.max_velocity, inp.max_acceleration, inp.max_jerk = [v], [a], [j]
    out = ruckig.Trajectory(1)
    try:
        res = ruckig.Ruckig(1).calculate(inp, out)
    except ruckig.RuckigError:  # a boundary acceleration that must overshoot the speed limit
        return None
    return float(out.duration) if res in (ruckig.Result.Working, ruckig.Result.Finished) else None


@settings(max_examples=300, deadline=None)
@given(d=st.floats(0.01, 60.0), v=st.floats(0.5, 10.0), a=st.floats(0.5, 10.0), j=st.floats(1.0, 60.0),
       f0=st.floats(-1.0, 1.0), f1=st.floats(-1.0, 1.0))
def test_no_stop_to_stop_motion_beats_the_run_time(d: float, v: float, a: float, j: float, f0: float,
                                                   f1: float) -> None:
    """ruckig's time-optimal v = 0 -> v = 0 motion, with any boundary accelerations, is never
    faster than run_time (which leaves them free)."""
    # a stop with acceleration a0 overshoots by a0^2 / 2J: beyond v, no curve within the bounds has it
    assume(max(f0 * f0, f1 * f1) * a * a / (2.0 * j) <= v)
    t = _ruckig_time(d, f0 * a, f1 * a, v, a, j)
    assume(t is not None)
    assert t is not None
    assert float(run_time(d, v, a, j)) <= t * (1 + 1e-9) + 1e-9


@settings(max_examples=200, deadline=None)
@given(d=st.floats(0.01, 40.0), a=st.floats(0.5, 10.0), j=st.floats(1.0, 60.0))
def test_the_a_j_bound_is_attained_without_a_speed_limit(d: float, a: float, j: float) -> None:
    """a(t) = clip(J (T/2 - t), -A, A) at T = run_time moves exactly d within |a| <= A, |jerk| <= J
    and stops: the bound is the true optimum of the problem it relaxes to, not merely valid."""
    t_end = float(run_time(d, np.inf, a, j))
    n = 20001
    t = np.linspace(0.0, t_end, n)
    acc = np.clip(j * (t_end / 2 - t), -a, a)
    dt = t[1] - t[0]
    vel = np.concatenate([[0.0], np.cumsum(0.5 * (acc[1:] + acc[:-1]) * dt)])
    pos = float(np.sum(0.5 * (vel[1:] + vel[:-1]) * dt))
    assert abs(vel[-1]) <= 1e-9 * max(1.0, a * t_end)
    assert np.max(np.abs(np.diff(acc))) <= j * dt * (1 + 1e-9)
    assert pos == pytest.approx(d, rel=1e-5, abs=1e-9)


def test_axis_runs_merge_monotone_steps_and_split_at_turns() -> None:
    assert axis_runs(np.array([0.0, 1.0, 3.0, 3.0, 2.0, 5.0])).tolist() == [3.0, 1.0, 3.0]
    assert axis_runs(np.array([1.0, 1.0])).size == 0


def _random_mission(rng: np.random.Generator) -> np.ndarray:
    wps = [np.zeros(3)]
    for _ in range(int(rng.integers(3, 8))):
        step = rng.normal(size=3) * np.array([1.0, 1.0, 0.3])
        wps.append(wps[-1] + step * rng.uniform(1.5, 8.0) / np.linalg.norm(step))
    return np.array(wps)


@pytest.mark.parametrize("seed", range(6))
def test_verified_fastest_plans_never_beat_the_bound(seed: int) -> None:
    """The planner's fastest verified plan (every bound held in continuous time) is never shorter
    than the bound; the bound contains the per-segment one the issue measures against."""
    rng = np.random.default_rng(seed)
    bounds = Bounds.symmetric(*(float(x) for x in rng.uniform([2.0, 2.0, 5.0, 20.0], [7.0, 7.0, 20.0, 80.0])))
    wps = _random_mission(rng)
    lb = flight_time_lower_bound(wps, bounds)
    vmax = bounds.hi[0]
    assert lb.per_segment == pytest.approx(float(np.sum(np.max(np.abs(np.diff(wps, axis=0)) / vmax, axis=1))))
    assert lb.value >= lb.per_segment and lb.value >= lb.turning
    problem = Problem.from_waypoints(wps, np.full(len(wps) - 1, 5.0), bounds)
    fast = fastest_durations(problem)
    assert fast.result.ok and fast.result.trajectory is not None
    traj = fast.result.trajectory
    flight = traj.t_end - traj.t0
    assert flight >= lb.value
    # squeezed below the bound, the fastest plan's durations plan no more
    squeezed = scaled_durations(fast.problem, 0.999 * lb.value / flight)
    assert not plan(squeezed, recover=False).ok
