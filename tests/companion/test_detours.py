"""Detours around obstacles that sit across a straight leg (route.plan_with_detours).

Scenes: a straight mission of 6 waypoints 4.5 m apart at 3 m altitude (NED z = -3); a
wall pops up across one leg while the vehicle flies; the remainder is re-planned from
the flown jet at the split, as the service does after a failed local replan.
"""

from __future__ import annotations

from itertools import pairwise

import numpy as np
import pytest

from companion.config import config_from_dict
from companion.detours import DETOUR_MARGIN, detour_candidates
from companion.edits import LocalEdit
from companion.mission import local_replan, replan_remainder, start_mission, trim
from companion.route import Outcome, Route
from companion.wire.messages import mission_from_message
from planner_core import first_hit, inflate
from planner_core.changes import AddObstacles
from planner_core.problem import Polytope, rest_jet
from planner_core.verify import verify

# (tracking_allowance 0: the walls below were laid out for the vehicle_radius margin alone)
CFG = config_from_dict({"geofence": {"min": [-50, -50, -20], "max": [50, 50, 0.5]},
                        "planner": {"tracking_allowance": 0.0}})
STEP = 4.5
WAYPOINTS = [[STEP * (i + 1), 0.0, -3.0] for i in range(6)]
X45 = 0.5 * (WAYPOINTS[4][0] + WAYPOINTS[5][0])  # mid-leg between mission waypoints 4 and 5


def box(lo: list[float], hi: list[float]) -> Polytope:
    eye = np.eye(3)
    return Polytope(np.vstack([eye, -eye]), np.concatenate([hi, -np.asarray(lo, dtype=float)]))


def wall_at(x: float, thick: float = 0.3, z: tuple[float, float] = (-4.0, -2.0), half_width: float = 1.0) -> Polytope:
    """2 m wide, 2 m tall (by default) and `thick` thick, across the leg at x."""
    return box([x - thick / 2, -half_width, z[0]], [x + thick / 2, half_width, z[1]])


def pillars(x: float) -> list[Polytope]:
    """Floor-to-ceiling columns either side of the leg near x: no way left or right."""
    return [box([x - 1.5, 1.4, -20.0], [x + 1.5, 3.5, 0.5]), box([x - 1.5, -3.5, -20.0], [x + 1.5, -1.4, 0.5])]


def fly(known: list[Polytope], msg: dict | None = None) -> Route:
    spec = mission_from_message({"id": "m", "waypoints": WAYPOINTS, **(msg or {})}, CFG)
    out = start_mission(spec, rest_jet(np.array([0.0, 0.0, -3.0])), 0.0, known, CFG)
    assert out.ok and out.route is not None, out.message
    return out.route


def assert_good_detour(route: Route, out: Outcome, t_split: float, obstacles: list[Polytope]) -> None:
    assert out.ok and out.route is not None, out.message
    new = out.route
    traj = new.trajectory
    assert out.stats["detour"], out.stats
    assert (new.labels == -1).sum() >= 2  # the split point and the detour point(s)
    assert verify(traj, new.problem).ok
    # continuous with what is being flown
    assert np.allclose(traj.jet(t_split), route.trajectory.jet(t_split), atol=1e-9)
    # every remaining mission waypoint, in order, exactly at its route time
    remaining = route.labels[route.times > t_split + 1e-6]
    mission = new.labels[new.labels >= 0]
    assert mission.tolist() == remaining.tolist()
    for i in np.flatnonzero(new.labels >= 0):
        wp = route.mission.waypoints[int(new.labels[i])]
        assert np.array_equal(new.waypoints[i], wp)
        assert np.allclose(traj.evaluate(new.times[i]), wp, atol=1e-9)
    assert np.allclose(traj.jet(traj.t_end)[1:], 0.0, atol=1e-9)  # ends at rest
    # dense samples stay clear of every obstacle inflated by the radius
    ts = np.arange(t_split, traj.t_end, 0.002)
    pts = traj.evaluate(ts)
    for ob in obstacles:
        assert not np.any(inflate(ob, route.mission.radius - 1e-6).contains(pts)), "enters an obstacle"
    lo, hi = route.mission.map_lo + route.mission.radius, route.mission.map_hi - route.mission.radius
    assert np.all(pts >= lo - 1e-6) and np.all(pts <= hi + 1e-6)


def popup(route: Route, t_split: float, known: list[Polytope], wall: Polytope) -> Outcome:
    """What the service does: the local replan first, then the remainder with detours."""
    assert first_hit(route.trajectory, t_split, [wall], route.mission.radius) is not None
    local = local_replan(trim(route, t_split - 0.15), t_split, LocalEdit((AddObstacles((wall,)),), "wall"), known, CFG)
    assert not local.ok  # no convex corridor holds a leg through a wall
    return replan_remainder(route, route.trajectory, t_split, [*known, wall], CFG)


@pytest.mark.parametrize(("name", "known", "wall", "t_split", "msg"), [
    ("beside, mid-leg 4 -> 5", [], wall_at(X45), 2.0, None),
    ("beside, a far obstacle listed first", [box([0.0, 10.0, -4.0], [1.0, 11.0, -2.0])], wall_at(X45), 2.0, None),
    ("beside, a 2 m box", [], wall_at(X45, thick=2.0), 2.0, None),
    ("beside, near waypoint 4", [], wall_at(WAYPOINTS[4][0] + 0.8), 2.0, None),
    ("beside, near waypoint 5", [], wall_at(WAYPOINTS[5][0] - 0.8), 2.0, None),
    ("beside, first leg after the split", [], wall_at(WAYPOINTS[1][0] - 1.5), 2.0, None),
    ("beside, 1.6 s ahead of the vehicle", [], wall_at(WAYPOINTS[1][0] + 2.0), -1.6, None),
    ("beside, one side outside the map", [], wall_at(X45), 2.0, {"map": {"min": [-50, -50, -20], "max": [50, 1.5, 0.5]}}),
    ("over, walled in on both sides", pillars(X45), wall_at(X45, z=(-4.0, 0.5)), 2.0, None),
    ("under, walled in on both sides", pillars(X45), wall_at(X45, z=(-20.0, -2.0)), 2.0, None),
])
def test_wall_across_a_leg_gets_a_verified_detour(name: str, known: list[Polytope], wall: Polytope,
                                                   t_split: float, msg: dict | None) -> None:
    route = fly(known, msg)
    if t_split < 0:  # that long before the flown plan would enter the inflated wall
        hit = first_hit(route.trajectory, 0.0, [wall], route.mission.radius)
        assert hit is not None
        t_split += hit
    out = popup(route, t_split, known, wall)
    assert_good_detour(route, out, t_split, [*known, wall])
    assert out.obstacle == len(known)  # the wall, as an index into the obstacles given
    assert out.stats["detour_obstacles"] == [len(known)]
    pts = np.asarray(out.stats["detour"])
    if name.startswith("over"):
        assert np.all(pts[:, 2] < -4.0)  # above the wall (NED: up is -z)
    elif name.startswith("under"):
        assert np.all(pts[:, 2] > -2.0)
    else:
        assert np.all(np.abs(pts[:, 1]) > 1.0) and np.allclose(pts[:, 2], -3.0)
        if msg is not None:  # y > 1.5 is outside the map: the other side
            assert np.all(pts[:, 1] < -1.0)


def test_two_walls_get_two_detours() -> None:
    route = fly([])
    first, second = wall_at(WAYPOINTS[2][0] + 2.0), wall_at(X45)
    out = replan_remainder(route, route.trajectory, 2.0, [first, second], CFG)
    assert_good_detour(route, out, 2.0, [first, second])
    assert sorted(out.stats["detour_obstacles"]) == [0, 1]
    assert len(out.stats["detour"]) == 4


def test_a_new_mission_through_a_wall_gets_a_detour() -> None:
    spec = mission_from_message({"id": "m", "waypoints": WAYPOINTS}, CFG)
    wall = wall_at(X45)
    out = start_mission(spec, rest_jet(np.array([0.0, 0.0, -3.0])), 0.0, [wall], CFG)
    assert out.ok and out.route is not None, out.message
    assert out.stats["detour"] and out.obstacle == 0
    ts = np.arange(0.0, out.route.trajectory.t_end, 0.002)
    assert not np.any(inflate(wall, spec.radius - 1e-6).contains(out.route.trajectory.evaluate(ts)))
    assert out.route.labels[out.route.labels >= 0].tolist() == list(range(len(WAYPOINTS)))


@pytest.mark.parametrize("blocker", [
    box([X45 - 0.15, -50.0, -20.0], [X45 + 0.15, 50.0, 0.5]),  # across the whole geofence
    box([X45 - 0.15, -50.0, -20.0], [X45 + 0.15, 50.0, 0.0]),  # a gap at the ground too low to pass
])
def test_no_free_space_is_a_refusal_that_names_the_obstacle(blocker: Polytope) -> None:
    known = [box([0.0, 10.0, -4.0], [1.0, 11.0, -2.0])]
    route = fly(known)
    out = replan_remainder(route, route.trajectory, 2.0, [*known, blocker], CFG)
    assert not out.ok and out.route is None
    assert out.obstacle == 1 and out.blocked_segment is not None
    assert "is blocked" in out.message and "no detour around obstacle '1'" in out.message


def test_detour_candidates_keep_clear_of_the_obstacle() -> None:
    a, b = np.array([0.0, 0.0, -3.0]), np.array([5.0, 0.0, -3.0])
    wall = wall_at(2.5)
    cands = detour_candidates(a, b, wall, 0.3)
    assert len(cands) == 4
    clear = 2 * 0.3 + DETOUR_MARGIN
    for pts in cands:
        path = np.vstack([a, pts, b])
        s = np.linspace(0.0, 1.0, 200)[:, None]
        dense = np.concatenate([p + s * (q - p) for p, q in pairwise(path)])
        assert not np.any(inflate(wall, clear - 1e-6).contains(dense))
