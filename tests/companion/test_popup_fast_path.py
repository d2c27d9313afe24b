"""The pop-up obstacle fast path: segment-culled first_hit and the incremental verification
of local replans."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from companion.edits import LocalEdit
from companion.mission import local_replan, trim
from companion.route import Outcome, Route
from planner_core import first_hit, inflate, verify_changed
from planner_core.changes import AddObstacles
from planner_core.problem import Polytope, Trajectory
from planner_core.verify import verify
from tests.companion.test_route import SLOW, box, fly


def brute_first_hit(traj, t_from, obstacles, radius, dt=0.01):  # type: ignore[no-untyped-def]
    ts = np.arange(t_from, traj.t_end + dt, dt)
    pts = traj.evaluate(ts)
    inside = np.zeros(len(ts), dtype=bool)
    for ob in obstacles:
        inside |= inflate(ob, radius).contains(pts, tol=-1e-9)
    return float(ts[int(np.argmax(inside))]) if np.any(inside) else None


def test_first_hit_equals_sampling_every_segment() -> None:
    r = fly([[3, 0, -1.5], [3, 3, -1.5], [0, 3, -1.5], [0, 0, -1.5]], [0, 0, -1.5])
    rng = np.random.default_rng(3)
    hits = 0
    for _ in range(60):
        c = rng.uniform([-0.5, -0.5, -2.0], [3.5, 3.5, -1.0])
        h = rng.uniform(0.05, 0.4, size=3)
        ob = box((c - h).tolist(), (c + h).tolist())
        t_from = float(rng.uniform(r.trajectory.t0, r.trajectory.t_end))
        expect = brute_first_hit(r.trajectory, t_from, [ob], 0.25)
        assert first_hit(r.trajectory, t_from, [ob], 0.25) == expect
        hits += expect is not None
    assert hits > 5  # the comparison saw real hits, not only misses


def popup_replan() -> tuple[Route, Outcome, Polytope]:
    # a plan with slack ([planner] timing = "default"): the local replan keeps later segments
    # bit for bit, which the incremental verification must recognise
    r = fly([[3, 0, -1.5], [3, 3, -1.5], [0, 3, -1.5], [0, 0, -1.5]], [0, 0, -1.5], cfg=SLOW)
    ob = box([3.55, 0.8, -3], [4.3, 2.2, 0])
    out = local_replan(trim(r, 2.0), 2.15, LocalEdit((AddObstacles((ob,)),), "avoid"), [], SLOW)
    assert out.ok and out.route is not None, out.message
    return r, out, ob


def test_incremental_verification_agrees_with_full_verify() -> None:
    r, out, _ = popup_replan()
    assert out.route is not None
    old = trim(r, 2.0)
    assert verify_changed(old.trajectory, old.problem, out.route.trajectory, out.route.problem) is None
    assert verify(out.route.trajectory, out.route.problem).ok


def test_incremental_verification_catches_a_bad_kept_corridor() -> None:
    r, out, _ = popup_replan()
    assert out.route is not None and out.route.problem.corridors is not None
    old = trim(r, 2.0)
    p, traj = out.route.problem, out.route.trajectory
    # a segment copied bit-for-bit from the old plan, under a corridor that cuts it
    s = next(k for k in range(traj.n_segments) if any(
        np.array_equal(traj.control_points[k], oc) for oc in old.trajectory.control_points))
    mid = traj.control_points[s].mean(axis=0)
    cut = Polytope(np.array([[1.0, 0.0, 0.0]]), np.array([mid[0]]))
    cors = list(p.corridors)
    cors[s] = cut
    bad = replace(p, corridors=tuple(cors))
    assert not verify(traj, bad).ok
    assert verify_changed(old.trajectory, old.problem, traj, bad) is not None


@pytest.mark.parametrize("what", ["control_point", "time"])
def test_incremental_verification_catches_a_changed_segment(what: str) -> None:
    r, out, _ = popup_replan()
    assert out.route is not None
    old = trim(r, 2.0)
    p, traj = out.route.problem, out.route.trajectory
    ctrl = traj.control_points.copy()
    times = traj.times.copy()
    s = traj.n_segments - 2
    if what == "control_point":
        ctrl[s, 4] += 0.5  # an interior point: waypoints stay, the snap/continuity does not
    else:
        times[s + 1] += 0.05
        p = replace(p, times=times)
    bad = Trajectory(times, ctrl, traj.corridors, traj.stats)
    assert not verify(bad, p).ok
    assert verify_changed(old.trajectory, old.problem, bad, p) is not None
