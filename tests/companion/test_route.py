from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest

from companion.braking import brake, corridor_at
from companion.config import Config, ConfigError, config_from_dict
from companion.edits import LocalEdit, Refused, resolve
from companion.mission import local_replan, replan_remainder, start_mission, trim
from companion.route import KNOT, Route, outside_map_text
from companion.wire.messages import (
    MessageError,
    change_from_message,
    mission_from_message,
    parse_region,
)
from planner_core import first_hit, splice, split_at
from planner_core import hold as hold_trajectory
from planner_core.changes import AddObstacles
from planner_core.problem import Polytope, rest_jet
from planner_core.verify import verify

# (tracking_allowance 0: the geometry below was laid out for the vehicle_radius margin alone)
CFG = config_from_dict({"planner": {"vehicle_radius": 0.25, "tracking_allowance": 0.0,
                                    "bounds": {"velocity": 3, "acceleration": 4, "jerk": 20, "snap": 120}}})


def box(lo: list[float], hi: list[float]) -> Polytope:
    eye = np.eye(3)
    return Polytope(np.vstack([eye, -eye]), np.concatenate([hi, -np.asarray(lo)]))


# [planner] timing = "default": slower plans, with slack everywhere (the default is "fastest")
SLOW = config_from_dict({"planner": {"vehicle_radius": 0.25, "tracking_allowance": 0.0, "timing": "default",
                                     "bounds": {"velocity": 3, "acceleration": 4, "jerk": 20, "snap": 120}}})


def fly(waypoints: list[list[float]], start: list[float], t0: float = 1.0, obstacles: tuple = (),
        cfg: Config = CFG) -> Route:
    spec = mission_from_message({"id": "m", "waypoints": waypoints}, cfg)
    out = start_mission(spec, rest_jet(np.asarray(start, dtype=float)), t0, list(obstacles), cfg)
    assert out.ok and out.route is not None, out.message
    return out.route


def test_mission_starts_at_the_current_state_and_is_verified() -> None:
    r = fly([[3, 0, -1.5], [3, 3, -1.5]], [0, 0, -1.5])
    assert r.labels.tolist() == [-1, 0, 1]
    assert np.allclose(r.trajectory.evaluate(1.0), [0, 0, -1.5])
    assert verify(r.trajectory, r.problem).ok
    assert r.trajectory.t0 == 1.0


@pytest.mark.parametrize("durations", [None, [4.0, 3.0]])
def test_mission_from_where_the_vehicle_already_is(durations: list[float] | None) -> None:
    """Waypoint 0 at the vehicle's position (within the arrival tolerance): no zero-length lead
    segment (its plan failed verification at the start); the current position stands for it."""
    msg: dict = {"id": "m", "waypoints": [[0, 0, -3], [3, 0, -3], [3, 3, -3]]}
    if durations is not None:
        msg["durations"] = durations
    spec = mission_from_message(msg, CFG)
    for start in ([0, 0, -3], [0.1, 0, -3]):
        out = start_mission(spec, rest_jet(np.asarray(start, dtype=float)), 1.0, [], CFG)
        assert out.ok and out.route is not None, out.message
        r = out.route
        assert r.labels.tolist() == [0, 1, 2]
        assert verify(r.trajectory, r.problem).ok
        assert np.allclose(r.trajectory.evaluate(1.0), start)
        if durations is not None:
            assert np.allclose(np.diff(r.times), durations)


def test_start_first_waypoint_requires_being_there() -> None:
    spec = mission_from_message({"id": "m", "start": "first_waypoint", "waypoints": [[0, 0, -1], [2, 0, -1]]}, CFG)
    far = start_mission(spec, rest_jet(np.array([1.0, 0, -1])), 0.0, [], CFG)
    assert not far.ok and "waypoint 0" in far.message
    near = start_mission(spec, rest_jet(np.array([0.05, 0, -1])), 0.0, [], CFG)
    assert near.ok and near.route is not None and near.route.labels[0] == 0
    assert near.route.labels[near.route.labels >= 0].tolist() == [0, 1]  # knots between are not counted


def test_start_first_waypoint_flies_on_from_the_flown_state() -> None:
    """Issue 20, real ArduCopter: home moves ~1 cm at arming, so a 'first_waypoint' mission sent
    from home lies a little off the hover it follows. The plan starts from the flown state (its
    position stands for waypoint 0), so it can be spliced on; a flown motion that is not the
    mission's `initial` is refused on field `initial`, not as an internal check."""
    spec = mission_from_message({"id": "m", "start": "first_waypoint", "waypoints": [[0, 0, -2], [4, 0, -2]]}, CFG)
    hover = rest_jet(np.array([0.012, -0.008, -1.99]))
    out = start_mission(spec, hover, 5.0, [], CFG)
    assert out.ok and out.route is not None, out.message
    assert np.array_equal(out.route.trajectory.evaluate(5.0), hover[0])  # exactly where the flight is
    assert np.allclose(out.route.trajectory.evaluate(5.0, 1), 0.0)
    assert out.route.labels[0] == 0 and verify(out.route.trajectory, out.route.problem).ok
    moving = hover.copy()
    moving[1] = [1.5, 0.0, 0.0]
    bad = start_mission(spec, moving, 5.0, [], CFG)
    assert not bad.ok and bad.field == "initial" and "start 'current'" in bad.message
    given = mission_from_message({"id": "m", "start": "first_waypoint", "waypoints": [[0, 0, -2], [4, 0, -2]],
                                  "initial": {"velocity": [1.5, 0.0, 0.0]}}, CFG)
    ok = start_mission(given, moving, 5.0, [], CFG)
    assert ok.ok and ok.route is not None, ok.message
    assert np.allclose(ok.route.trajectory.evaluate(5.0, 1), [1.5, 0.0, 0.0])


def test_splice_keeps_the_flown_piece_and_fills_waits_with_a_hold() -> None:
    hold = hold_trajectory(np.array([0.0, 0, -1.5]), 0.0)
    r = fly([[3, 0, -1.5]], [0, 0, -1.5], t0=2.5)  # starts after the hold's span ended
    spliced = splice(hold, r.trajectory)
    ts = np.linspace(0, 2.5, 50)
    assert np.allclose(spliced.evaluate(ts), [0, 0, -1.5])
    ts = np.linspace(2.5, r.trajectory.t_end, 50)
    assert np.array_equal(spliced.evaluate(ts), r.trajectory.evaluate(ts))
    # where the new plan begins (published with it): the segments from there on are its own
    assert spliced.stats["spliced_at"] == 2.5
    first = int(np.searchsorted(spliced.times, spliced.stats["spliced_at"]))
    assert np.array_equal(spliced.control_points[first:], r.trajectory.control_points)
    # A split inside a segment is exact (de Casteljau).
    split, k = split_at(r.trajectory, 3.3)
    ts = np.linspace(r.trajectory.t0, r.trajectory.t_end, 300)
    assert np.allclose(split.evaluate(ts), r.trajectory.evaluate(ts), atol=1e-12)
    assert split.times[k] == 3.3


def test_popup_obstacle_local_replan_keeps_prefix_and_clears_obstacle() -> None:
    r = fly([[3, 0, -1.5], [3, 3, -1.5], [0, 3, -1.5]], [0, 0, -1.5])
    ob = box([3.55, 0.8, -3], [4.3, 2.2, 0])
    assert first_hit(r.trajectory, 1.0, [ob], 0.25) is not None
    t_now = 2.0
    out = local_replan(trim(r, t_now), t_now + 0.15, LocalEdit((AddObstacles((ob,)),), "avoid"), [], CFG)
    assert out.ok and out.route is not None, out.message
    new = out.route.trajectory
    ts = np.linspace(t_now, t_now + 0.15, 30)
    assert np.max(np.abs(new.evaluate(ts) - r.trajectory.evaluate(ts))) <= 1e-12
    assert first_hit(new, t_now, [ob], 0.25 - 1e-6) is None
    assert len(out.route.labels) == out.route.problem.m


def test_blocked_waypoint_is_named_in_mission_indices() -> None:
    r = fly([[3, 0, -1.5], [3, 3, -1.5], [0, 3, -1.5]], [0, 0, -1.5])
    wall = box([2.5, 2.5, -3], [3.5, 3.5, 0])
    out = replan_remainder(r, r.trajectory, 2.0, [wall], CFG)
    assert not out.ok and out.blocked_waypoint == 1
    assert "mission waypoint 1 is blocked" in out.message


def local_edit(r: Route, change: dict, t_split: float) -> LocalEdit:
    """The change read as the service reads it (wire, then edits.resolve); a refusal raised."""
    resolved = resolve(r, change_from_message(change, CFG), t_split)
    if isinstance(resolved, Refused):
        raise MessageError(resolved.field, resolved.reason)
    assert resolved.local is not None
    return resolved.local


def test_change_edits_map_mission_indices_to_the_route() -> None:
    r = fly([[3, 0, -1.5], [3, 3, -1.5], [0, 3, -1.5]], [0, 0, -1.5])
    e = local_edit(r, {"insert_waypoint": {"index": 2, "position": [2, 4, -1.5]}}, 1.2)
    labels = e.relabel(r.labels, lambda i: i)
    assert labels.tolist() == [-1, 0, 1, 2, 3]
    assert e.labels == ("insert", 3, 2)
    e = local_edit(r, {"remove_waypoint": {"index": 1}}, 1.2)
    assert e.relabel(r.labels, lambda i: i).tolist() == [-1, 0, 1]
    with pytest.raises(MessageError) as info:
        local_edit(r, {"move_waypoint": {"index": 7, "position": [0, 0, -1]}}, 1.2)
    assert info.value.field == "move_waypoint.index"
    with pytest.raises(MessageError) as info:
        local_edit(r, {"move_waypoint": {"index": 0, "position": [0, 500, -1]}}, 1.2)
    assert info.value.field == "move_waypoint.position"
    out = local_replan(trim(r, 1.5), 1.65, local_edit(trim(r, 1.5), {"move_waypoint": {"index": 2, "position": [0, 3.5, -1.5]}}, 1.65), [], CFG)
    assert out.ok and out.route is not None, out.message
    assert np.allclose(out.route.waypoints[out.route.labels == 2], [0, 3.5, -1.5])


def test_braking_stops_inside_the_corridor() -> None:
    r = fly([[4, 0, -1.5]], [0, 0, -1.5])
    t = 0.5 * (r.trajectory.t0 + r.trajectory.t_end)
    jet = r.trajectory.jet(t)
    assert np.linalg.norm(jet[1]) > 0.5
    corridor = corridor_at(r.trajectory, t)
    traj, why = brake(jet, r.mission.bounds, corridor, t)
    assert traj is not None, why
    end = traj.jet(traj.t_end)
    assert np.allclose(end[1:], 0, atol=1e-9)
    assert np.allclose(traj.jet(t), jet, atol=1e-9)


@pytest.mark.parametrize("cfg", [CFG, SLOW], ids=["fastest", "default"])
def test_obstacle_across_the_path_gets_a_detour(cfg: Config) -> None:
    r = fly([[6, 0, -1.5], [6, 3, -1.5]], [0, 0, -1.5], cfg=cfg)
    allocated = cfg.planner.timing == "fastest"
    assert np.any(r.labels == KNOT) == allocated  # the fastest plan puts knots on the 6 m leg
    block = box([3.5, -0.6, -2.5], [4.3, 0.6, -0.5])  # across the straight leg, over a knot
    # the service's fallback for a pop-up: durations the mission did not give are allocated again
    out = replan_remainder(r, r.trajectory, 2.0, [block], cfg, allocate=allocated)
    assert out.ok and out.route is not None, out.message
    assert out.stats["detour"]
    assert (out.route.labels == -1).sum() >= 2  # the split point and the detour point(s)
    mission = out.route.labels[out.route.labels >= 0]
    assert mission.tolist() == [0, 1] and out.route.labels[-1] == 1
    assert first_hit(out.route.trajectory, 2.0, [block], 0.25 - 1e-6) is None
    assert verify(out.route.trajectory, out.route.problem).ok


@pytest.mark.parametrize(("region", "field", "words"), [
    ({"A": [[1, 0, 0]], "b": [1]}, "add[0]", "unbounded"),
    ({"A": np.vstack([np.eye(3), -np.eye(3)]).tolist(), "b": [-1, 1, 1, -1, 1, 1]}, "add[0]", "empty"),
    ({"vertices": [[0, 0, 0], [1, 0, 0], [2, 0, 0], [3, 0, 0]]}, "add[0].vertices", "collinear"),
])
def test_obstacles_must_be_bounded_and_solid(region: dict, field: str, words: str) -> None:
    with pytest.raises(MessageError) as info:
        parse_region({"id": "o", **region}, "add[0]")
    assert info.value.field == field and words in info.value.reason


def test_fastest_timing_flies_faster_keeps_mission_indices_and_verifies() -> None:
    """[planner] timing = "fastest" (the default): a mission without durations gets the fastest
    allocation; knots it puts on long legs are synthetic waypoints (KNOT), never counted as mission
    waypoints."""
    wps = [[12, 0, -1.5], [12, 3, -1.5], [0, 3, -1.5]]
    spec = mission_from_message({"id": "m", "waypoints": wps}, CFG)
    start = rest_jet(np.array([0.0, 0.0, -1.5]))
    slow = start_mission(spec, start, 1.0, [], SLOW)
    quick = start_mission(spec, start, 1.0, [], CFG)
    assert slow.ok and quick.ok and slow.route is not None and quick.route is not None, quick.message
    r = quick.route
    assert r.t_end < slow.route.t_end
    assert verify(r.trajectory, r.problem).ok
    assert np.count_nonzero(r.labels == KNOT) > 0  # knots were inserted
    mission_labels = r.labels[r.labels >= 0]
    assert mission_labels.tolist() == [0.0, 1.0, 2.0]  # in order, each once
    for i, p in enumerate(wps):
        k = int(np.flatnonzero(r.labels == i)[0])
        assert np.allclose(r.trajectory.evaluate(r.times[k]), p, atol=1e-6)
    with pytest.raises(Exception, match="timing"):
        config_from_dict({"planner": {"timing": "quickest"}})


@pytest.mark.parametrize("reserve", [0.0, 0.2, 0.4])
def test_reserve_leaves_a_share_of_every_bound_unused_for_replans(reserve: float) -> None:
    """[planner] reserve: an allocated mission flies within (1 - reserve) x the bounds by dense
    sampling, while its problem (what replans are checked against) keeps the full bounds; a
    larger reserve flies slower."""
    cfg = config_from_dict({"planner": {"vehicle_radius": 0.25, "tracking_allowance": 0.0, "reserve": reserve,
                                        "bounds": {"velocity": 3, "acceleration": 4, "jerk": 20, "snap": 120}}})
    r = fly([[6, 0, -1.5], [6, 3, -1.5], [2, 4, -2.0]], [0, 0, -1.5], cfg=cfg)
    assert np.array_equal(r.problem.bounds.hi, r.mission.bounds.hi)
    ts = np.linspace(r.trajectory.t0, r.trajectory.t_end, 4000)
    for k in range(1, 5):
        peak = np.max(np.abs(r.trajectory.evaluate(ts, k)) / r.mission.bounds.hi[k - 1])
        assert peak <= (1.0 - reserve) * (1 + 1e-6), (k, peak)
    tighter = fly([[6, 0, -1.5], [6, 3, -1.5], [2, 4, -2.0]], [0, 0, -1.5], cfg=replace(
        cfg, planner=replace(cfg.planner, reserve=reserve + 0.2)))
    assert tighter.t_end > r.t_end


@pytest.mark.parametrize("value", [-0.1, 0.9, 1.5])
def test_reserve_is_a_share_below_one(value: float) -> None:
    with pytest.raises(ConfigError, match=r"planner\.reserve"):
        config_from_dict({"planner": {"reserve": value}})


def test_a_position_too_near_the_map_box_says_how_near_not_outside() -> None:
    """A landed PX4 SIH whose home was reported 0.35 m above it sat inside the box, 0.12 m above
    its floor: the refusal said "below the floor ... by more than the vehicle radius", which it was
    not. Inside but too near a face: how far inside; beyond it: how far beyond."""
    box = SimpleNamespace(map_lo=[-100, -100, -50], map_hi=[100, 100, 0.5], radius=0.45, frame="ned")
    labels = np.array([-1.0])

    def said(p: list[float]) -> str | None:
        return outside_map_text(box, np.array([p], dtype=float), labels, 0)  # type: ignore[arg-type]

    assert "is 1.10 m below the floor of the map box" in str(said([0, 0, 1.6]))
    assert "is only 0.30 m above the floor of the map box" in str(said([0, 0, 0.2]))
    assert "is 0.20 m outside the map box" in str(said([100.2, 0, 0])) and "on axis x" in str(said([100.2, 0, 0]))
    assert "is only 0.20 m inside the map box" in str(said([99.8, 0, 0]))
    assert "radius 0.45 m" in str(said([0, 0, 0.2]))
    assert said([0, 0, 0]) is None
