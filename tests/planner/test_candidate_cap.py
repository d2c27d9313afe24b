"""Issue 25 / 21: the fastest-allocation search cut to a number of candidate plans (what the
companion can afford before its split on a busy computer). The cap is a count, not a clock: the
same cap gives the same plan; the answer is always a verified plan, never slower than the
default allocation, and a larger cap never flies slower."""

from __future__ import annotations

import itertools

import numpy as np
import pytest

from planner_core import Bounds, Polytope, Problem, fastest_durations, verify

BOUNDS = Bounds.symmetric(3.0, 3.0, 10.0, 50.0)  # companion/config.py [planner.bounds]


def _square() -> Problem:
    """The lifecycle test's mission flown from the start with 1 m/s along x."""
    wps = np.array([[0.0, 0.0, -1.5], [4.0, 0.0, -1.5], [4.0, 4.0, -1.5], [0.0, 4.0, -1.5], [0.0, 0.0, -1.5]])
    p = Problem.from_waypoints(wps, np.ones(4), BOUNDS)
    initial = p.initial.copy()
    initial[1] = [1.0, 0.0, 0.0]
    return Problem(p.waypoints, p.times, p.bounds, initial, p.final, p.corridors)


def _cluttered() -> Problem:
    wps = np.array([[0.0, 0.0, 1.0], [3.0, 1.0, 1.0], [6.0, 0.0, 1.5], [9.0, 2.0, 1.0]])
    eye = np.eye(3)
    box = Polytope(np.concatenate([eye, -eye]), np.array([12.0, 5.0, 4.0, 2.0, 5.0, 1.0]))
    return Problem.from_waypoints(wps, np.ones(3), BOUNDS, (box,) * 3)


@pytest.mark.parametrize("make", [_square, _cluttered], ids=["square", "cluttered"])
def test_a_capped_search_is_verified_deterministic_and_no_slower_with_more(make: object) -> None:
    problem = make()  # type: ignore[operator]
    full = fastest_durations(problem)
    assert full.ok and not full.result.stats["allocation"]["capped"]
    flight = {}
    for cap in (1, 2, 4, 8):
        a = fastest_durations(problem, max_candidates=cap)
        assert a.ok and a.result.trajectory is not None
        assert a.plans <= cap, (cap, a.plans)  # the default allocation held: no more than the cap
        assert a.result.stats["allocation"]["capped"] == (a.plans >= cap)
        assert verify(a.result.trajectory, a.problem).ok
        flight[cap] = float(a.durations.sum())
        again = fastest_durations(problem, max_candidates=cap)
        assert np.array_equal(again.result.trajectory.control_points, a.result.trajectory.control_points)
    caps = sorted(flight)
    for lo, hi in itertools.pairwise(caps):
        assert flight[hi] <= flight[lo] + 1e-9, flight
    assert float(full.durations.sum()) <= flight[8] + 1e-9
    # 8 candidates already find most of what the whole search (~30) finds: within 10 %
    assert flight[8] <= 1.1 * float(full.durations.sum()), (flight, float(full.durations.sum()))


def test_the_cap_never_leaves_the_search_without_an_answer() -> None:
    """Candidates that fail do not count against the cap until one holds: a fast start (2.5 m/s,
    2.5 m/s^2 across) 0.5 m before a turn, whose default allocation does not plan, still ends in
    a verified plan under cap 1, found by stretching past the cap."""
    p = Problem.from_waypoints(np.array([[0.0, 0.0, -1.5], [0.5, 0.0, -1.5], [0.5, 0.5, -1.5]]), np.ones(2), BOUNDS)
    initial = p.initial.copy()
    initial[1], initial[2] = [2.5, 0.0, 0.0], [0.0, 2.5, 0.0]
    problem = Problem(p.waypoints, p.times, p.bounds, initial, p.final, p.corridors)
    a = fastest_durations(problem, max_candidates=1, search=True)
    assert a.ok and a.result.trajectory is not None and verify(a.result.trajectory, a.problem).ok
    assert a.plans > 1 and a.scale > 1.4  # the default allocation (scale 1.4) failed first
    with pytest.raises(ValueError, match="max_candidates"):
        fastest_durations(problem, max_candidates=0)
