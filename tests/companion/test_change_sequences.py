"""Changes in sequence, as the navigator applies them: each one resolved against the route
as it is when it arrives (trimmed to now), with mission indices as published."""

from __future__ import annotations

import json

import numpy as np
import pytest

from companion.config import config_from_dict
from companion.edits import Refused, Resolved, resolve, resolve_planned
from companion.flight import State, refuse_command
from companion.mission import local_replan, remaining, replan_remainder, start_mission, trim
from companion.obstacles import Known
from companion.route import KNOT, Route
from companion.wire.messages import (
    Change,
    MessageError,
    MoveChange,
    change_from_message,
    mission_from_message,
    read,
)
from planner_core import rest_jet, verify

CFG = config_from_dict({"planner": {"vehicle_radius": 0.25,
                                    "bounds": {"velocity": 3, "acceleration": 4, "jerk": 20, "snap": 120}}})
SIX = [[3.0 * i, 0.5 * (i % 2), -3.0] for i in range(1, 7)]


def flying(waypoints: list[list[float]]) -> Route:
    spec = mission_from_message({"id": "six", "waypoints": waypoints}, CFG)
    out = start_mission(spec, rest_jet(np.array([0.0, 0.0, -3.0])), 0.0, Known(), CFG)
    assert out.ok and out.route is not None, out.message
    return out.route


def apply(route: Route, change: Change, now: float, split: float = 0.3) -> Route:
    """What Navigator.on_change does: trim, resolve, local replan, else the remainder."""
    r = trim(route, now)
    resolved = resolve_planned(r, change, now + split, r.mission.durations is None)  # CFG: timing "fastest"
    assert isinstance(resolved, Resolved), resolved
    out = None
    if resolved.local is not None:
        out = local_replan(r, now + split, resolved.local, Known(), CFG)
    if out is None or not out.ok:
        out = replan_remainder(r, route.trajectory, now + split, Known(), CFG,
                               resolved.waypoints, resolved.times, resolved.labels, allocate=resolved.allocate)
    assert out.ok and out.route is not None, out.message
    assert verify(out.route.trajectory, out.route.problem).ok
    return out.route


def passes(route: Route, point: list[float]) -> float:
    """Distance from `point` to the nearest waypoint the route's plan passes through."""
    ends = np.concatenate([route.trajectory.control_points[:, 0], route.trajectory.control_points[-1:, -1]])
    return float(np.min(np.linalg.norm(ends - np.asarray(point), axis=1)))


def move(index: int, position: list[float]) -> Change:
    return change_from_message({"move_waypoint": {"index": index, "position": position}}, CFG)


@pytest.mark.parametrize("first_at", [0.5, 3.0])
def test_two_moves_in_a_row_each_move_the_waypoint_they_name(first_at: float) -> None:
    r0 = flying(SIX)
    new4, new3 = [15.0, 0.9, -3.0], [12.0, -0.4, -3.0]  # 0.4 m from SIX[4], SIX[3]
    r1 = apply(r0, move(4, new4), first_at)
    # the vehicle flies on (waypoints 0, 1 passed) before the second change
    t2 = float(r1.times[r1.labels == 2][0]) + 0.2
    assert t2 < float(r1.times[r1.labels == 3][0]) - 0.5, "test geometry: waypoint 3 still ahead"
    r2 = apply(r1, move(3, new3), t2)
    assert passes(r2, new4) <= 1e-6 and passes(r2, new3) <= 1e-6
    assert np.allclose(r2.waypoints[r2.labels == 4], new4) and np.allclose(r2.waypoints[r2.labels == 3], new3)
    # every waypoint still ahead is there, in mission order
    ahead = r2.labels[r2.labels >= 0]
    assert ahead.tolist() == sorted(ahead.tolist()) and ahead[-1] == 5


def test_a_passed_waypoint_is_refused_naming_what_is_still_ahead() -> None:
    r = flying(SIX)
    t = float(r.times[r.labels == 2][0]) + 0.1
    got = resolve(trim(r, t), move(1, [3.0, 1.0, -3.0]), t + 0.3)
    assert isinstance(got, Refused) and got.field == "move_waypoint.index"
    assert "already been passed" in got.reason and "[3, 4, 5]" in got.reason


def test_what_a_stop_leaves_keeps_the_mission_indices() -> None:
    r = flying(SIX)
    t = float(r.times[r.labels == 2][0]) + 0.1
    left = remaining(r, t)
    assert left is not None and left.first_index == 3 and np.allclose(left.waypoints, SIX[3:])
    out = start_mission(left, rest_jet(np.array(r.trajectory.evaluate(t))), 50.0, Known(), CFG)
    assert out.ok and out.route is not None
    assert out.route.labels[out.route.labels >= 0].tolist() == [3, 4, 5]
    # a change after resuming names the mission's own index
    moved = apply(out.route, move(4, [15.0, 0.9, -3.0]), 50.2)
    assert passes(moved, [15.0, 0.9, -3.0]) <= 1e-6


def test_enu_positions_are_named_in_enu_with_plain_numbers() -> None:
    bad = read("change", json.dumps({"frame": "enu", "move_waypoint": {"index": 1, "position": [10.0, 500.0, 3.0]}}).encode(), CFG)
    assert isinstance(bad, MessageError) and bad.field == "move_waypoint.position"
    assert "[10, 500, 3] (ENU)" in bad.reason and "np.float64" not in bad.reason
    assert "[-100, -100, -0.5]..[100, 100, 50]" in bad.reason  # the geofence in ENU (up from -0.5 m)
    ok = read("change", json.dumps({"frame": "enu", "move_waypoint": {"index": 1, "position": [1.0, 2.0, 3.0]}}).encode(), CFG)
    assert isinstance(ok, Change) and isinstance(ok.body, MoveChange) and np.allclose(ok.body.position, [2.0, 1.0, -3.0])


@pytest.mark.parametrize("state", [State.FAILSAFE, State.PILOT, State.IDLE, State.STREAMING, State.BRAKING,
                                   State.HOLDING, State.READY, State.TAKEOFF])
def test_land_is_accepted_whenever_the_vehicle_is_armed(state: State) -> None:
    assert refuse_command(state, "land", armed=True, auto_arm=False, has_mission=False) is None
    assert refuse_command(state, "land", armed=False, auto_arm=False, has_mission=False) is not None


def test_an_armed_vehicle_on_the_ground_does_not_hold_or_resume() -> None:
    for cmd in ("hold", "resume"):
        assert refuse_command(State.READY, cmd, armed=True, auto_arm=False, has_mission=True, airborne=False)
        assert refuse_command(State.READY, cmd, armed=True, auto_arm=False, has_mission=True, airborne=True) is None


LONG = [[12.0, 0.0, -3.0], [12.0, 3.0, -3.0], [0.0, 3.0, -3.0]]  # 12 m legs: the fastest plan puts knots on them


def test_changes_on_a_fastest_plan_are_read_between_mission_waypoints_not_knots() -> None:
    """The planner's knots are not mission waypoints: a set duration counts from mission
    waypoint to mission waypoint, and a moved waypoint's legs are replanned without the old
    knots (which lay on the old straight legs)."""
    r0 = flying(LONG)
    assert np.any(r0.labels == KNOT)
    # 1. mission waypoint 1 moved 1.5 m sideways and 1 m up, while the vehicle flies to waypoint 0
    new1 = [12.0, 1.5, -2.0]
    r1 = apply(r0, move(1, new1), 0.5)
    assert passes(r1, new1) <= 1e-6
    i0, i1 = int(np.flatnonzero(r1.labels == 0)[0]), int(np.flatnonzero(r1.labels == 1)[0])
    a, b = r1.waypoints[i0], r1.waypoints[i1]
    for p in r1.waypoints[i0 + 1 : i1]:  # whatever lies between is on the new straight leg
        assert np.linalg.norm(np.cross(b - a, p - a)) / np.linalg.norm(b - a) <= 1e-6
    assert r1.labels[r1.labels >= 0].tolist() == [0, 1, 2]
    # 2. segment 1 (mission waypoints 1 -> 2, knots between) set to 9 s
    at = float(r1.times[r1.labels == 0][0]) + 0.3
    r2 = apply(r1, change_from_message({"duration": {"index": 1, "value": 9.0}}, CFG), at)
    t1, t2 = (float(r2.times[r2.labels == i][0]) for i in (1, 2))
    assert t2 - t1 == pytest.approx(9.0, abs=1e-6)
    assert r2.labels[r2.labels >= 0].tolist() == [0, 1, 2]


def test_changes_that_give_times_keep_them_on_an_allocated_mission() -> None:
    """On a mission without durations the remainder is allocated again after a change, unless
    the change gives times (a set duration, appended durations): those are flown as given, and
    the navigator keeps the mission's times from then on (Replans.user_timed)."""
    r = flying(LONG)
    t = 0.5
    cases = [
        ({"duration": {"index": 1, "value": 9.0}}, False),
        ({"append": {"waypoints": [[0.0, 0.0, -3.0]], "durations": [4.0]}}, False),
        ({"append": {"waypoints": [[0.0, 0.0, -3.0]]}}, True),
        ({"move_waypoint": {"index": 1, "position": [12.0, 2.0, -3.0]}}, True),
    ]
    for msg, allocates in cases:
        got = resolve_planned(trim(r, t), change_from_message(msg, CFG), t + 0.3, True)
        assert isinstance(got, Resolved), got
        assert got.allocate is allocates and got.sets_times is not allocates, msg
        kept = resolve_planned(trim(r, t), change_from_message(msg, CFG), t + 0.3, False)
        assert isinstance(kept, Resolved) and not kept.allocate  # a timed mission keeps its times
    appended = apply(r, change_from_message(cases[1][0], CFG), t)
    last = int(np.flatnonzero(appended.labels == 3)[0])
    assert appended.times[last] - appended.times[last - 1] == pytest.approx(4.0, abs=1e-6)
