"""The braking deadline and the stop planned for it (route.brake_deadline, route.plan_stop), and
the setpoint loop's garbage-collection pacing. Real QPs, no service."""

from __future__ import annotations

import gc
from collections.abc import Iterator

import numpy as np
import pytest

from companion.braking import BRAKE_MARGIN_SECONDS, MIN_STOP_SECONDS, brake_deadline, plan_stop
from companion.route import Route
from companion.runtime import GcPacer
from planner_core import (
    Bounds,
    FloatArray,
    Neighbours,
    certify_separation,
    first_hit,
    inflate,
    splice,
)
from planner_core.problem import Polytope, Trajectory
from tests.companion.test_route import box, fly

RADIUS = 0.25


def across() -> tuple[Route, Polytope, float]:
    """A straight leg and a box across it: (route, obstacle, time the leg enters it inflated)."""
    r = fly([[0.0, 6.0, -1.5]], [0.0, 0.0, -1.5], t0=0.0)
    ob = box([-0.8, 4.4, -2.5], [0.8, 5.0, -0.5])
    hit = first_hit(r.trajectory, 0.0, [ob], RADIUS)
    assert hit is not None
    return r, ob, hit


def enters(traj: Trajectory, ob: Polytope, t0: float) -> bool:
    ts = np.linspace(t0, traj.t_end, 2000)
    return bool(np.any(inflate(ob, RADIUS).contains(traj.evaluate(ts), tol=-1e-9)))


def within_bounds(traj: Trajectory, bounds: Bounds) -> bool:
    ts = np.linspace(traj.t0, traj.t_end, 400)
    for order in (1, 2):
        d = traj.evaluate(ts, order)
        if np.any(d > bounds.hi[order - 1] + 1e-6) or np.any(d < bounds.lo[order - 1] - 1e-6):
            return False
    return True


def test_deadline_leaves_a_stop_before_the_hit_and_a_stop_from_it_stays_clear() -> None:
    r, ob, hit = across()
    now = 0.5
    deadline = brake_deadline(r.trajectory, now, hit, r.mission.bounds)
    assert now < deadline <= hit - MIN_STOP_SECONDS - BRAKE_MARGIN_SECONDS
    plan = plan_stop(r.trajectory, [deadline], lambda: now, [ob], r.mission, r.mission.bounds, 0.08)
    stop = plan.trajectory
    assert stop is not None and plan.in_free_space
    assert plan.start == pytest.approx(deadline)  # the latest start asked for was feasible
    spliced = splice(r.trajectory, stop)
    ts = np.linspace(now, deadline, 50)
    assert np.allclose(spliced.evaluate(ts), r.trajectory.evaluate(ts), atol=1e-9)
    assert np.allclose(stop.jet(stop.t0), r.trajectory.jet(deadline), atol=1e-6)
    assert np.linalg.norm(stop.evaluate(np.array([stop.t_end]), 1)) <= 1e-9  # at rest
    assert not enters(spliced, ob, now)
    assert within_bounds(stop, r.mission.bounds)


def test_stop_never_starts_before_the_clock_plus_lead() -> None:
    r, ob, hit = across()
    late = hit - 0.9  # the deadline has passed: brake as soon as possible
    plan = plan_stop(r.trajectory, [late - 0.5], lambda: late, [ob], r.mission, r.mission.bounds, 0.08)
    assert plan.trajectory is not None
    assert plan.start >= late + 0.08 - 1e-12
    if plan.in_free_space:
        assert not enters(plan.trajectory, ob, plan.start)


def test_a_stop_planned_too_slowly_is_planned_again_further_ahead() -> None:
    r, ob, _ = across()
    ticks: Iterator[float] = iter(np.arange(1.0, 100.0, 0.06))  # every clock reading 60 ms later

    def clock() -> float:
        return float(next(ticks))

    plan = plan_stop(r.trajectory, [1.0], clock, [ob], r.mission, r.mission.bounds, 0.05)
    assert plan.trajectory is not None
    # the first attempt (start 1.05) finished at 1.12, after its start: not returned
    assert plan.start > 1.12


def test_no_free_corridor_falls_back_to_a_dynamic_stop_and_says_so() -> None:
    r, _, _ = across()
    t = 2.0
    here = r.trajectory.evaluate(np.array([t + 0.1]))[0]
    engulfing = box((here - 1.0).tolist(), (here + 1.0).tolist())  # the vehicle is inside it
    plan = plan_stop(r.trajectory, [t], lambda: t, [engulfing], r.mission, r.mission.bounds, 0.08)
    assert plan.trajectory is not None
    # inside the obstacle there is no free corridor: the flown segment's corridor (no pop-ups
    # in it) or the bounds alone, and the plan says so
    assert not plan.in_free_space
    assert "no free corridor around the vehicle" in plan.message
    assert "flown segment's corridor" in plan.message or "dynamic bounds only" in plan.message
    assert within_bounds(plan.trajectory, r.mission.bounds)


@pytest.fixture
def pacer() -> Iterator[GcPacer]:
    p = GcPacer(young=100, full_every=1.0, slack=0.008)
    yield p
    p.stop()
    gc.unfreeze()


def test_gc_pacer_turns_automatic_collection_off_and_collects_on_the_loops_terms(pacer: GcPacer) -> None:
    pacer.start(now=0.0)
    assert not gc.isenabled() and gc.get_freeze_count() > 0
    junk = [[i] for i in range(500)]  # tracked objects: the young count grows
    assert gc.get_count()[0] >= 100
    pacer.after_send(now=0.1, next_deadline=0.105)  # 5 ms of slack: too little
    assert pacer.collections == [0, 0, 0]
    pacer.after_send(now=0.1, next_deadline=0.12)
    assert sum(pacer.collections[:2]) == 1 and pacer.collections[2] == 0
    assert gc.get_count()[0] < 100
    pacer.after_send(now=1.5, next_deadline=1.52)  # a full collection is due
    assert pacer.collections[2] == 1 and pacer.worst > 0.0
    del junk
    pacer.stop()
    assert gc.isenabled()


# -- in a fleet: the stop chosen separated from the other vehicles (issue 24.4) -----------------


def crossing(rest: FloatArray, t_end: float) -> Trajectory:
    """Another vehicle's trajectory across the leg, through `rest` about 1 s after `t_end`."""
    return fly([[3.0, float(rest[1]), float(rest[2])]], [-3.0, float(rest[1]), float(rest[2])], t0=t_end - 1.0).trajectory


def test_a_stop_in_a_fleet_is_chosen_separated_from_the_others() -> None:
    r, ob, _ = across()
    now = 1.0
    plain = plan_stop(r.trajectory, [1.5], lambda: now, [ob], r.mission, r.mission.bounds, 0.08)
    assert plain.trajectory is not None and plain.separated is None  # no fleet: not judged
    other = crossing(plain.trajectory.control_points[-1, -1], plain.trajectory.t_end)
    nb = Neighbours((other,), 1.0)
    # the shortest stop rests where the other vehicle passes a second later
    assert not certify_separation(plain.trajectory, other, 1.0).ok
    plan = plan_stop(r.trajectory, [1.5], lambda: now, [ob], r.mission, r.mission.bounds, 0.08, nb, ("drone7",))
    stop = plan.trajectory
    assert stop is not None and plan.separated is True and plan.in_free_space
    assert certify_separation(stop, other, 1.0).ok  # checked independently of the choice
    assert now + 0.08 - 1e-12 <= plan.start <= 1.5
    assert np.allclose(stop.jet(stop.t0), r.trajectory.jet(plan.start), atol=1e-6)
    assert np.linalg.norm(stop.evaluate(np.array([stop.t_end]), 1)) <= 1e-9
    assert within_bounds(stop, r.mission.bounds) and not enters(splice(r.trajectory, stop), ob, now)
    assert "drone7" in plan.message and "neighbour" not in plan.message, plan.message


def test_a_stop_no_candidate_of_which_is_separated_is_flown_and_says_from_whom() -> None:
    r, ob, _ = across()
    now = 1.0
    # the other vehicle holds 0.5 m beside the leg for ever: no stop from it keeps 3 m
    beside = fly([[0.5, 2.0, -1.5]], [0.5, 1.9, -1.5], t0=0.0).trajectory
    plan = plan_stop(r.trajectory, [1.5], lambda: now, [ob], r.mission, r.mission.bounds, 0.08,
                     Neighbours((beside,), 3.0), ("drone7",))
    stop = plan.trajectory
    assert stop is not None and plan.in_free_space and plan.separated is False
    assert not certify_separation(stop, beside, 3.0).ok
    assert "not separated from the other vehicles" in plan.message and "drone7" in plan.message, plan.message
    assert plan.start == pytest.approx(1.5)  # the asked start's shortest stop: the obstacle comes first
    assert not enters(splice(r.trajectory, stop), ob, now)
