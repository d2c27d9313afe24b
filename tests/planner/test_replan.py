"""Local replanning, exact splitting and the braking trajectory, on real QPs.

Every replan result is checked with the full certificate (verify) and by
comparing control points: segments the change does not touch must be
bit-identical to the trajectory before the change.
"""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from planner_core.braking import braking_trajectory
from planner_core.changes import (
    AddObstacles,
    AppendWaypoints,
    ChangeError,
    ChangeSet,
    InsertWaypoint,
    MoveWaypoint,
    RemoveWaypoint,
    SetCorridor,
    SetDuration,
    box,
    parse_change,
)
from planner_core.formats.io import load_scenario, trajectory_from_dict, trajectory_to_dict
from planner_core.planning import plan
from planner_core.problem import Bounds, Polytope, Problem, Trajectory
from planner_core.replan import (
    Environment,
    ReplanOptions,
    ReplanResult,
    replan,
    split_problem_at,
)
from planner_core.replan import (
    split_inside as split_at,
)
from planner_core.result import PlanStatus
from planner_core.verify import verify

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def _load(name: str) -> dict:
    return json.loads((EXAMPLES / name).read_text())


@pytest.fixture(scope="module")
def scenario2():  # type: ignore[no-untyped-def]
    return load_scenario(_load("scenario2.json"))


@pytest.fixture(scope="module")
def planned2(scenario2):  # type: ignore[no-untyped-def]
    res = plan(scenario2.problem)
    assert res.ok and res.trajectory is not None, res.message
    problem = replace(scenario2.problem, times=res.trajectory.times.copy())
    return problem, res.trajectory


@pytest.fixture(scope="module")
def env2(scenario2) -> Environment:  # type: ignore[no-untyped-def]
    return Environment(tuple(scenario2.obstacles), scenario2.map_box, scenario2.vehicle_radius)


def _ok(res: ReplanResult) -> Trajectory:
    assert res.status is PlanStatus.OK, res.message
    assert res.trajectory is not None
    report = verify(res.trajectory, res.problem)
    assert report.ok, report.summary()
    return res.trajectory


def _changed(old: np.ndarray, new: np.ndarray, mapping: dict[int, int]) -> set[int]:
    """New segments that are not bit-identical to their old counterpart (mapping new -> old)."""
    return {s for s in range(new.shape[0]) if s not in mapping or not np.array_equal(new[s], old[mapping[s]])}


def _touching(jets: tuple[int, ...], n_seg: int) -> set[int]:
    return {s for j in jets for s in (j - 1, j) if 0 <= s < n_seg}


# --- parsing -------------------------------------------------------------------


def test_parse_change_all_kinds() -> None:
    cs = parse_change(
        {
            "from_time": 3.5,
            "move": [{"index": 2, "position": [1, 2, 3]}],
            "duration": {"segment": 1, "duration": 4},
            "corridor": {"segment": 0, "corridor": {"min": [0, 0, 0], "max": [1, 1, 1]}},
            "obstacles": [{"center": [15, 4.5, 1], "size": [2, 1, 2]}],
            "insert": {"index": 3, "position": [0, 0, 0]},
            "append": {"waypoints": [[1, 1, 1]], "durations": [2.0]},
        }
    )
    kinds = {type(e) for e in cs.edits}
    assert kinds == {MoveWaypoint, SetDuration, SetCorridor, AddObstacles, InsertWaypoint, AppendWaypoints}
    assert cs.from_time == 3.5
    obstacle = next(e for e in cs.edits if isinstance(e, AddObstacles)).obstacles[0]
    assert obstacle.contains(np.array([15.0, 4.5, 1.0]))[0]
    assert not obstacle.contains(np.array([15.0, 5.2, 1.0]))[0]
    # the spelling of examples/scenario2_move.json
    move = parse_change(_load("scenario2_move.json")).edits[0]
    assert isinstance(move, MoveWaypoint) and move.index == 2
    # and the companion schema's spellings
    dur = parse_change({"duration": {"index": 3, "value": 2.5}}).edits[0]
    assert isinstance(dur, SetDuration) and (dur.segment, dur.duration) == (3, 2.5)
    ins = parse_change({"insert_waypoint": {"index": 2, "position": [1, 2, 3]}}).edits[0]
    assert isinstance(ins, InsertWaypoint) and ins.index == 2
    rem = parse_change({"remove_waypoint": {"index": 4}}).edits[0]
    assert isinstance(rem, RemoveWaypoint) and rem.index == 4


@pytest.mark.parametrize(
    ("obj", "field"),
    [
        ({"move": {"index": 2}}, "move.position"),
        ({"move": {"index": "2", "position": [0, 0, 0]}}, "move.index"),
        ({"move": [{"index": 1, "position": [0, 0]}]}, "move[0].position"),
        ({"duration": {"segment": 1, "duration": -1}}, "duration.duration"),
        ({"obstacles": [{"A": [[1, 0]], "b": [1]}]}, "obstacles[0]"),
        ({"append": {"waypoints": [[0, 0, 0]], "durations": [1, 2]}}, "append.durations"),
        ({"insert": {"index": 1, "position": [0, 0, 0]}, "remove": {"index": 2}}, "insert"),
        ({"teleport": 1}, "teleport"),
        ({}, "change"),
    ],
)
def test_parse_change_errors_name_the_field(obj: dict, field: str) -> None:
    with pytest.raises(ChangeError) as err:
        parse_change(obj)
    assert err.value.field == field


# --- split -------------------------------------------------------------------------


def test_split_at_is_exact(planned2) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned2
    rng = np.random.default_rng(3)
    for t in rng.uniform(traj.t0 + 0.1, traj.t_end - 0.1, size=5):
        new = split_at(traj, float(t))
        assert new.n_segments == traj.n_segments + 1
        assert t in new.times
        ts = np.linspace(traj.t0, traj.t_end, 2001)
        assert np.max(np.abs(new.evaluate(ts) - traj.evaluate(ts))) <= 1e-12
        for k in range(1, 5):
            a, b = new.evaluate(ts, k), traj.evaluate(ts, k)
            assert np.max(np.abs(a - b) / (1.0 + np.abs(b))) <= 1e-9
        p2, t2, k = split_problem_at(problem, traj, float(t))
        assert p2.m == problem.m + 1 and t2.times[k] == t
        assert p2.corridors is not None and p2.corridors[k - 1] is p2.corridors[k]
        assert verify(t2, p2).ok
    with pytest.raises(ValueError, match="coincides"):
        split_at(traj, float(traj.times[2]))
    with pytest.raises(ValueError, match="inside"):
        split_at(traj, traj.t_end + 1.0)


# --- each change kind ------------------------------------------------------------


def test_move_waypoint_resolves_only_its_jet(planned2) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned2
    res = replan(problem, traj, MoveWaypoint(4, np.array([6.0, 10.3, 1.2])))
    new = _ok(res)
    assert res.resolved_jets == (4,)
    assert np.allclose(new.evaluate(new.times[4]), [6.0, 10.3, 1.2], atol=1e-12)
    n = traj.n_segments
    assert _changed(traj.control_points, new.control_points, {s: s for s in range(n)}) == {3, 4}


def test_duration_change(planned2) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned2
    d = float(problem.times[4] - problem.times[3])
    res = replan(problem, traj, SetDuration(3, d + 1.0))
    new = _ok(res)
    assert res.resolved_jets == (3, 4)
    assert np.isclose(new.times[4] - new.times[3], d + 1.0)
    assert np.allclose(new.times[5:], traj.times[5:] + 1.0)
    changed = _changed(traj.control_points, new.control_points, {s: s for s in range(traj.n_segments)})
    assert changed == _touching(res.resolved_jets, traj.n_segments)


def test_corridor_change_resolves_only_when_violated(planned2) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned2
    s = 2
    ctrl = traj.control_points[s]
    loose = box(ctrl.min(axis=0) - 1.0, ctrl.max(axis=0) + 1.0)
    res = replan(problem, traj, SetCorridor(s, loose))
    new = _ok(res)
    assert res.resolved_jets == ()
    assert np.array_equal(new.control_points, traj.control_points)
    # a face that cuts the current curve (but keeps both waypoints inside) forces a re-solve
    lo = ctrl.min(axis=0) - 1.0
    hi = ctrl.max(axis=0) + 1.0
    hi[1] = max(problem.waypoints[s, 1], problem.waypoints[s + 1, 1]) + 0.6
    tight = box(lo, hi)
    assert tight.violation(ctrl) > 0.0
    res = replan(problem, traj, SetCorridor(s, tight))
    new = _ok(res)
    assert set(res.resolved_jets) >= {s, s + 1}
    assert tight.violation(new.control_points[s]) <= 1e-9
    changed = _changed(traj.control_points, new.control_points, {i: i for i in range(traj.n_segments)})
    assert changed == _touching(res.resolved_jets, traj.n_segments)


def test_insert_waypoint(planned2) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned2
    pos = np.array([10.5, 5.2, 1.0])  # on segment 2 ([15,5,1] -> [6,5,1])
    res = replan(problem, traj, InsertWaypoint(3, pos))
    new = _ok(res)
    assert res.problem.m == problem.m + 1
    assert np.array_equal(res.problem.waypoints[3], pos)
    assert 3 in res.resolved_jets
    mapping = {s: s for s in range(2)} | {s: s - 1 for s in range(4, new.n_segments)}
    assert _changed(traj.control_points, new.control_points, mapping) == _touching(res.resolved_jets, new.n_segments)
    assert np.allclose(new.times[[0, 1, 2, 4, 5]], traj.times[[0, 1, 2, 3, 4]])


def test_remove_waypoint(planned2, env2) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned2
    opts = ReplanOptions(environment=env2)
    # every waypoint of the serpentine is needed, so first add one on the free lane x = 15
    added = replan(problem, traj, InsertWaypoint(6, np.array([15.0, 12.5, 1.0])), options=opts)
    before = _ok(added)
    res = replan(added.problem, before, RemoveWaypoint(6), options=opts)
    new = _ok(res)
    assert res.problem.m == problem.m
    assert set(res.resolved_jets) >= {5, 6}
    mapping = {s: s for s in range(5)} | {s: s + 1 for s in range(6, new.n_segments)}
    assert _changed(before.control_points, new.control_points, mapping) == _touching(
        res.resolved_jets, new.n_segments
    )
    with pytest.raises(ChangeError) as err:  # no environment: the merged corridor is unknown
        replan(added.problem, before, RemoveWaypoint(6))
    assert err.value.field == "remove.corridor"


def test_append_grows_the_mission(planned2, env2) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned2
    extra = np.array([[3.0, 15.0, 1.0], [3.0, 17.0, 1.5]])
    res = replan(problem, traj, AppendWaypoints(extra, np.array([3.0, 3.0])), options=ReplanOptions(environment=env2))
    new = _ok(res)
    m = problem.m
    assert res.problem.m == m + 2
    assert set(res.resolved_jets) >= {m - 1, m}
    assert np.allclose(new.jet(new.t_end)[1:], 0.0, atol=1e-9)
    assert np.allclose(new.evaluate(new.t_end), extra[-1], atol=1e-12)
    changed = _changed(traj.control_points, new.control_points, {s: s for s in range(traj.n_segments)})
    assert changed == _touching(res.resolved_jets, new.n_segments)
    # and again: a mission can keep growing
    res2 = replan(res.problem, new, AppendWaypoints(np.array([[1.0, 17.0, 1.5]]), np.array([2.0])),
                  options=ReplanOptions(environment=res.environment))
    assert _ok(res2).n_segments == new.n_segments + 1


def test_long_append_goes_through_the_iterative_pass() -> None:
    rng = np.random.default_rng(2)
    steps = rng.uniform([2, -3, -0.5], [5, 3, 0.5], (20, 3))
    wps = np.cumsum(steps, axis=0)
    problem = Problem.from_waypoints(wps[:6], np.full(5, 2.0), Bounds.symmetric(7, 6.5, 40, 400))
    res0 = plan(problem)
    assert res0.ok and res0.trajectory is not None
    traj = res0.trajectory
    res = replan(problem, traj, AppendWaypoints(wps[6:], np.full(14, 2.0)))
    new = _ok(res)
    assert res.problem.m == 20 and res.resolved_jets == tuple(range(5, 19))
    assert np.array_equal(new.control_points[:4], traj.control_points[:4])


def test_from_time_keeps_the_past(planned2) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned2
    t = float(0.5 * (traj.times[3] + traj.times[4]))  # inside segment 3
    change = ChangeSet((MoveWaypoint(5, np.array([15.0, 10.4, 1.0])),), from_time=t)
    res = replan(problem, traj, change)
    new = _ok(res)
    k = res.stats["split_index"]
    assert k == 4 and new.times[k] == t
    assert all(j > k for j in res.resolved_jets)
    assert np.array_equal(new.control_points[:3], traj.control_points[:3])
    ts = np.linspace(traj.t0, t, 500)
    assert np.max(np.abs(new.evaluate(ts) - traj.evaluate(ts))) <= 1e-12
    # the piece after the split is the exact remainder where nothing was re-solved
    assert res.resolved_jets == (6,)
    assert np.array_equal(new.control_points[-1], traj.control_points[-1])
    # a change of the past is refused
    with pytest.raises(ChangeError) as err:
        replan(problem, traj, ChangeSet((MoveWaypoint(2, np.array([15.0, 5.2, 1.0])),), from_time=t))
    assert err.value.field == "move.index"


def test_from_time_never_frees_the_split_jet(planned2) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned2
    t = float(traj.times[3] + 0.2)
    # moving the waypoint right after the split: only jets after it may change
    res = replan(problem, traj, ChangeSet((MoveWaypoint(4, np.array([6.0, 10.2, 1.0])),), from_time=t))
    new = _ok(res)
    k = res.stats["split_index"]
    assert min(res.resolved_jets) > k
    left = split_at(traj, t)
    assert np.array_equal(new.control_points[: k], left.control_points[: k])


# --- infeasible and widening -----------------------------------------------------


def test_infeasible_change_reports(planned2) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned2
    far = np.array([6.0, 10.0, 40.0])  # outside the corridors (and the map)
    res = replan(problem, traj, MoveWaypoint(4, far))
    assert res.status is PlanStatus.INFEASIBLE and res.trajectory is None
    assert "waypoint 4" in res.message and "corridor" in res.message
    assert res.problem is problem
    # kinodynamically impossible: a 35 m jump within the same time (3 s at <= 7 m/s), no corridors
    free = replace(problem, corridors=None)
    tr = replace(traj, corridors=None)
    res = replan(free, tr, MoveWaypoint(4, np.array([6.0, 45.0, 1.0])), options=ReplanOptions(max_stretch=0))
    assert res.status is PlanStatus.INFEASIBLE
    assert "no feasible local replan" in res.message


def test_widening_recovers_when_the_seed_is_infeasible() -> None:
    # Slow straight line (a 2 m/s^2 bound and a 2 m move: with less the subdivided certificate
    # lets the seed through); moving W3 forward with both neighbours' jets fixed
    # needs more acceleration than allowed, freeing the neighbours does not.
    wps = np.array([[4.0 * i, 0.0, 0.0] for i in range(7)])
    problem = Problem.from_waypoints(wps, np.full(6, 2.0), Bounds.symmetric(6, 2, np.inf, np.inf))
    res0 = plan(problem)
    assert res0.ok and res0.trajectory is not None
    traj = res0.trajectory
    move = MoveWaypoint(3, wps[3] + np.array([2.0, 0.0, 0.0]))
    narrow = replan(problem, traj, move, options=ReplanOptions(max_widen=0, max_stretch=0))
    assert narrow.status is PlanStatus.INFEASIBLE
    res = replan(problem, traj, move, options=ReplanOptions(max_stretch=0))
    new = _ok(res)
    assert res.stats["widened"] >= 1
    assert set(res.resolved_jets) > {3}
    changed = _changed(traj.control_points, new.control_points, {s: s for s in range(traj.n_segments)})
    assert changed == _touching(res.resolved_jets, traj.n_segments)


def test_stretching_recovers_when_widening_is_not_allowed() -> None:
    wps = np.array([[4.0 * i, 0.0, 0.0] for i in range(7)])
    problem = Problem.from_waypoints(wps, np.full(6, 2.0), Bounds.symmetric(6, 2, np.inf, np.inf))
    res0 = plan(problem)
    assert res0.ok and res0.trajectory is not None
    traj = res0.trajectory
    move = MoveWaypoint(3, wps[3] + np.array([2.0, 0.0, 0.0]))
    res = replan(problem, traj, move, options=ReplanOptions(max_widen=0, max_stretch=2))
    new = _ok(res)
    assert res.stats["stretched"] >= 1 and set(res.resolved_jets) <= {2, 3, 4}
    # the touched segments got longer, everything after shifts in time but keeps its shape
    assert new.times[3] - new.times[2] > traj.times[3] - traj.times[2]
    shift = new.times[-1] - traj.times[-1]
    assert shift > 0 and np.allclose(new.times[5:], traj.times[5:] + shift)
    changed = _changed(traj.control_points, new.control_points, {s: s for s in range(traj.n_segments)})
    assert changed == _touching(res.resolved_jets, traj.n_segments)


def test_hull_violation_names_the_failure(planned2) -> None:  # type: ignore[no-untyped-def]
    from planner_core.certificate import hull_violation

    problem, traj = planned2
    d = np.diff(traj.times)
    corr = list(traj.corridors)
    assert hull_violation(traj.control_points, d, problem.bounds, corr) is None
    tight = problem.bounds.scaled(0.3)
    msg = hull_violation(traj.control_points, d, tight, corr)
    assert msg is not None and "bound exceeded" in msg
    assert not verify(traj, replace(problem, bounds=tight)).ok
    shifted = traj.control_points + np.array([0.0, 0.0, 5.0])
    msg = hull_violation(shifted, d, problem.bounds, corr, labels=list(range(10, 17)))
    assert msg is not None and msg.startswith("corridor violated") and msg.endswith("segment 10")


def test_insert_time_must_lie_inside_the_segment(planned2) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned2
    with pytest.raises(ChangeError) as err:
        replan(problem, traj, InsertWaypoint(3, np.array([10.5, 5.0, 1.0]), time=float(traj.times[5])))
    assert err.value.field == "insert.time"
    with pytest.raises(ChangeError) as err:
        replan(problem, traj, MoveWaypoint(problem.m, np.zeros(3)))
    assert err.value.field == "move.index"


# --- the paper's scenario 2 ------------------------------------------------------


def _box_distance(points: np.ndarray, poly: Polytope) -> np.ndarray:
    lo = -poly.b[3:]
    hi = poly.b[:3]
    return np.linalg.norm(np.maximum(np.maximum(lo - points, points - hi), 0.0), axis=1)


def test_scenario2_popup_obstacle_flow(planned2, env2) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned2
    popup = _load("scenario2_popup.json")
    opts = ReplanOptions(environment=env2)
    # 1. the pop-up obstacle swallows waypoint 2 ([15, 5, 1]) inflated by the radius
    res = replan(problem, traj, parse_change(popup), options=opts)
    assert res.status is PlanStatus.INFEASIBLE
    assert res.diagnosis is not None and res.diagnosis["waypoint"] == 2
    assert "waypoint 2" in res.message
    # 2. the paper's new waypoint [15, 5.8, 1]: the straight segment from [15, 0, 1]
    #    still runs through the (centred) box, so no convex corridor exists: reported
    res = replan(problem, traj, parse_change({**popup, **_load("scenario2_move.json")}), options=opts)
    assert res.status is PlanStatus.INFEASIBLE
    assert res.diagnosis is not None and res.diagnosis["segment"] == 1
    assert "segment 1 (waypoint 1 -> 2)" in res.message
    # 3. a clear new position for waypoint 2: only its jet is re-solved
    change = parse_change({**popup, "move": {"index": 2, "position": [18.5, 6.4, 1.0]}})
    res = replan(problem, traj, change, options=opts)
    new = _ok(res)
    # jet 2 alone cannot reach the detour under scenario 2's jerk/snap bounds, so the
    # set widens by one neighbour each side, and no further; the rest stays bit-identical
    assert 2 in res.resolved_jets and set(res.resolved_jets) <= {1, 2, 3}
    assert (res.resolved_jets == (2,)) == (not res.stats.get("widened"))
    changed = _changed(traj.control_points, new.control_points, {s: s for s in range(traj.n_segments)})
    assert {1, 2} <= changed <= _touching(res.resolved_jets, traj.n_segments)
    obstacle = next(e for e in change.edits if isinstance(e, AddObstacles)).obstacles[0]
    ts = np.linspace(new.t0, new.t_end, 4000)
    assert np.min(_box_distance(new.evaluate(ts), obstacle)) >= env2.radius - 1e-9
    assert res.environment is not None and len(res.environment.obstacles) == len(env2.obstacles) + 1


def test_scenario2_paper_move_without_obstacle(planned2) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned2
    res = replan(problem, traj, parse_change(_load("scenario2_move.json")))
    new = _ok(res)
    assert res.resolved_jets == (2,)
    assert _changed(traj.control_points, new.control_points, {s: s for s in range(traj.n_segments)}) == {1, 2}


# --- braking ------------------------------------------------------------------------


def test_braking_from_random_moving_states() -> None:
    bounds = Bounds.symmetric(7.0, 6.5, 40.0, 400.0)
    corridor = box(np.array([-20.0, -20.0, -5.0]), np.array([20.0, 20.0, 5.0]))
    rng = np.random.default_rng(11)
    for _ in range(12):
        jet = np.zeros((5, 3))
        jet[0] = rng.uniform([-8, -8, -2], [8, 8, 2])
        jet[1] = rng.uniform(-5.0, 5.0, 3)
        jet[2] = rng.uniform(-3.0, 3.0, 3)
        jet[3] = rng.uniform(-10.0, 10.0, 3)
        jet[4] = rng.uniform(-50.0, 50.0, 3)
        res = braking_trajectory(jet, bounds, corridor, t0=7.0)
        assert res.status is PlanStatus.OK, res.message
        traj = res.trajectory
        assert traj is not None and traj.t0 == 7.0
        start = traj.jet(traj.t0)
        assert np.allclose(start[0], jet[0], atol=1e-9)
        assert np.allclose(start[1:], jet[1:], rtol=1e-6, atol=1e-6)
        assert np.allclose(traj.jet(traj.t_end)[1:], 0.0, atol=1e-9)
        assert corridor.violation(traj.control_points.reshape(-1, 3)) <= 1e-9
        problem = Problem(traj.waypoints, traj.times, bounds, jet, traj.jet(traj.t_end), (corridor,) * traj.n_segments)
        assert verify(traj, problem).ok


def test_braking_along_a_flown_trajectory(planned2) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned2
    from planner_core.bezier import locate

    for t in np.linspace(0.05, traj.t_end - 0.05, 16):
        s = int(locate(traj.times, np.array([t]))[0][0])
        jet = traj.jet(float(t))
        # near a turn only the next corridor leaves room to stop: both are candidates
        res = braking_trajectory(jet, problem.bounds, traj.corridors[s : s + 2], t0=float(t))
        assert res.ok and res.trajectory is not None, res.message
        stop = res.trajectory
        region = traj.corridors[s + res.stats["corridor_candidate"]]
        assert region.violation(stop.control_points.reshape(-1, 3)) <= 1e-9
        # at rest, to the rounding of a k-th derivative of stored control points (eps |P| 9!/(9-k)!
        # / d^k: verify's floor; 1e-8 of snap on this plan's last stop)
        assert np.allclose(stop.jet(stop.t_end)[1:], 0.0, atol=1e-6)
        start = stop.jet(float(t))  # derivatives from control points of a short lead segment
        assert np.allclose(start[0], jet[0], atol=1e-9)
        # the same floor on a short lead segment: 2e-6 of snap (of 0.37 m/s^4) on this plan
        assert np.allclose(start[1:], jet[1:], rtol=1e-6, atol=1e-5)


def test_braking_infeasible_cases() -> None:
    bounds = Bounds.symmetric(7.0, 6.5, np.inf, np.inf)
    corridor = box(np.array([-5.0, -5.0, -5.0]), np.array([5.0, 5.0, 5.0]))
    outside = np.zeros((5, 3))
    outside[0] = [6.0, 0.0, 0.0]
    res = braking_trajectory(outside, bounds, corridor)
    assert res.status is PlanStatus.INFEASIBLE and "outside the corridor" in res.message
    wall = np.zeros((5, 3))
    wall[0] = [4.8, 0.0, 0.0]
    wall[1] = [6.5, 0.0, 0.0]  # 0.2 m from the wall at 6.5 m/s, 6.5 m/s^2: cannot stop
    res = braking_trajectory(wall, bounds, corridor)
    assert res.status is PlanStatus.INFEASIBLE and "no braking trajectory" in res.message
    fast = np.zeros((5, 3))
    fast[1] = [9.0, 0.0, 0.0]
    res = braking_trajectory(fast, bounds, corridor)
    assert res.status is PlanStatus.INFEASIBLE and "velocity" in res.message
    free = braking_trajectory(wall, bounds, None)  # without the wall it can stop
    assert free.ok


# --- CLI ----------------------------------------------------------------------------


def test_cli_replan(tmp_path: Path, planned2) -> None:  # type: ignore[no-untyped-def]
    from planner_core.formats.cli import main

    _, traj = planned2
    traj_path = tmp_path / "traj.json"
    traj_path.write_text(json.dumps(trajectory_to_dict(traj, "enu")))
    out = tmp_path / "new.json"
    scenario = str(EXAMPLES / "scenario2.json")
    rc = main(["replan", scenario, str(traj_path), str(EXAMPLES / "scenario2_move.json"), "-o", str(out)])
    assert rc == 0
    new = trajectory_from_dict(json.loads(out.read_text()))
    assert new.n_segments == traj.n_segments
    assert np.allclose(new.evaluate(new.times[2]), [15.0, 5.8, 1.0], atol=1e-12)
    assert np.array_equal(new.control_points[3:], traj.control_points[3:])
    rc = main(["replan", scenario, str(traj_path), str(EXAMPLES / "scenario2_popup.json"), "-o", str(out)])
    assert rc == 3
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"move": {"index": 99, "position": [0, 0, 0]}}))
    assert main(["replan", scenario, str(traj_path), str(bad), "-o", str(out)]) == 2
    bad.write_text("{not json")
    assert main(["replan", scenario, str(traj_path), str(bad), "-o", str(out)]) == 2
