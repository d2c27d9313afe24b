"""Horizontal norm bounds (issue 26.2): certified on a polygon inscribed in the disc, in every
planner path, in `verify`, in time allocation and braking, and in the file formats."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from planner_core import (
    Bounds,
    IterativeOptions,
    MoveWaypoint,
    Polytope,
    Problem,
    allocate_times,
    bounds_to_dict,
    braking_trajectory,
    plan,
    plan_mission,
    replan,
    stop_time_scale,
    verify,
)
from planner_core.constraints import (
    bound_layout,
    bound_sides,
    hull_maps,
    polygon_normals,
    segment_rows,
)
from planner_core.formats.io import ScenarioError, load_scenario
from planner_core.jets import ProblemCache
from planner_core.timing import directional_bounds

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"
DENSE = 20001


def _hnorm(traj, order: int) -> np.ndarray:  # type: ignore[no-untyped-def]
    t = np.linspace(traj.t0, traj.t_end, DENSE)
    d = traj.evaluate(t, order)
    return np.asarray(np.hypot(d[:, 0], d[:, 1]))


def _vehicle(vh: float = 3.0, ah: float = 2.5) -> Bounds:
    return Bounds.vehicle(horizontal=(vh, ah, 8.0, 30.0), up=(2.5, 1.0, 8.0, 30.0), down=(1.5, 1.0, 8.0, 30.0))


# --- the polygon ------------------------------------------------------------------------


def test_polygon_is_inscribed_and_loses_what_it_says() -> None:
    """Every point satisfying the half-planes is inside the disc (the vertices are on it), and the
    polygon reaches r along the axes, r cos(pi/N) at its edges' midpoints."""
    for sides in (4, 8, 16, 32):
        n = polygon_normals(sides)
        lim = np.cos(np.pi / sides)
        ang = 2 * np.pi * np.arange(sides) / sides
        verts = np.stack([np.cos(ang), np.sin(ang)], axis=1)
        assert np.all(np.abs(verts @ n.T).max(axis=1) <= lim + 1e-12)  # vertices on the boundary
        # any point of the polygon is a convex combination of vertices: inside the unit disc
        rng = np.random.default_rng(sides)
        w = rng.dirichlet(np.ones(sides), size=2000)
        assert np.all(np.linalg.norm(w @ verts, axis=1) <= 1.0 + 1e-12)
        # the loss: the smallest reach (the edge midpoints) is cos(pi / N)
        theta = np.linspace(0, 2 * np.pi, 10001)
        u = np.stack([np.cos(theta), np.sin(theta)], axis=1)
        reach = lim / np.abs(u @ n.T).max(axis=1)
        assert reach.min() == pytest.approx(lim, rel=1e-6) and reach.max() == pytest.approx(1.0, rel=1e-9)
    assert 1 - np.cos(np.pi / 16) < 0.02


def test_bounds_api() -> None:
    b = Bounds.vehicle(horizontal=(5, 4, np.inf, np.inf), up=(2.5, 1, 10, 40), down=(1.5, 1, 10, 40))
    assert np.array_equal(b.lo[:, 2], [-2.5, -1, -10, -40]) and np.array_equal(b.hi[:, 2], [1.5, 1, 10, 40])  # NED
    assert np.all(np.isinf(b.lo[:, :2])) and b.has_norm and b.sides == 16
    lo, hi = b.axis_limits()
    assert np.array_equal(hi[:2, :2], [[5, 5], [4, 4]]) and np.array_equal(lo[:2, :2], -hi[:2, :2]) and np.isinf(hi[2, 0])
    z_up = Bounds.vehicle(horizontal=(5, 4, 9, 9), up=(2.5, 1, 9, 9), down=(1.5, 1, 9, 9), z_up=True)
    assert z_up.hi[0, 2] == 2.5 and z_up.lo[0, 2] == -1.5
    boxed = Bounds.vehicle(horizontal=(5, 4, 9, 9), up=(2.5, 1, 9, 9), down=(1.5, 1, 9, 9), box=Bounds.symmetric(3, 3, 3, 3))
    assert boxed.hi[0, 0] == 3 and boxed.hi[0, 2] == 1.5 and boxed.horizontal[0] == 5
    assert not Bounds.symmetric(1, 1, 1, 1).has_norm
    assert np.array_equal(b.scaled(0.5).horizontal[:2], [2.5, 2])
    with pytest.raises(ValueError, match="horizontal"):
        Bounds(b.lo, b.hi, horizontal=np.array([1.0, -1.0, np.inf, np.inf]))
    with pytest.raises(ValueError, match="sides"):
        Bounds(b.lo, b.hi, horizontal=b.horizontal, sides=7)
    with pytest.raises(ValueError, match="up"):
        Bounds.vehicle(horizontal=(5, 4, 9, 9), up=(0, 1, 9, 9), down=(1, 1, 9, 9))


def test_box_only_rows_are_the_per_axis_rows() -> None:
    """Without a norm bound the bound rows are exactly the per-axis rows (point * 3 + axis, the
    kron with I3, the [start | both | end] permutation) they were before norm bounds existed."""
    box = Bounds.symmetric(3, 2, 5, 9)
    lay = bound_layout(box)
    n = lay.point.size // 3
    assert np.array_equal(lay.point, np.repeat(np.arange(n), 3)) and np.array_equal(lay.code, np.tile(np.arange(3), n))
    hull = hull_maps(np.array([1.7]))[0]
    rows = segment_rows(hull, box, None)
    old = np.kron(hull[10:], np.eye(3))
    assert np.array_equal(rows.rows, old)
    a_only, b_only = bound_sides()
    assert np.array_equal(lay.start_only, a_only) and np.array_equal(lay.end_only, b_only)
    wps = np.array([[0.0, 0, 0], [3, 1, 0], [5, 4, 1]])
    cache = ProblemCache(Problem.from_waypoints(wps, [3.0, 3.0], box))
    both = ~a_only & ~b_only
    perm = np.concatenate([np.flatnonzero(a_only), np.flatnonzero(both), np.flatnonzero(b_only)])
    A, B, c0 = cache.bound_rows(0)
    qb = hull_maps(np.array([3.0]))[0][10:]
    old_a = np.einsum("rc,de->rdce", qb[:, 1:5], np.eye(3)).reshape(-1, 12)[perm]
    old_b = np.einsum("rc,de->rdce", qb[:, 6:10], np.eye(3)).reshape(-1, 12)[perm]
    old_c0 = (qb[:, 0, None] * wps[0] + qb[:, 5, None] * wps[1]).reshape(-1)[perm]
    assert np.array_equal(A, old_a) and np.array_equal(B, old_b) and np.array_equal(c0, old_c0)
    # with a norm bound: the polygon's rows come on top, two-sided, at r cos(pi / N)
    normed = _vehicle()
    lay_n = bound_layout(normed)
    extra = lay_n.point.size - lay.point.size
    n_v = int(np.sum(lay.order[::3] == 1))
    n_a = int(np.sum(lay.order[::3] == 2))
    assert extra == (n_v + n_a + int(np.sum(lay.order[::3] == 3)) + int(np.sum(lay.order[::3] == 4))) * 8
    vel = (lay_n.code == 3) & (lay_n.order == 1)
    assert np.allclose(lay_n.hi[vel], 3.0 * np.cos(np.pi / 16)) and np.allclose(lay_n.lo[vel], -3.0 * np.cos(np.pi / 16))


# --- plans within the norm --------------------------------------------------------------


@st.composite
def _scenes(draw: st.DrawFn) -> tuple[np.ndarray, float, float]:
    m = draw(st.integers(3, 6))
    steps = draw(st.lists(st.tuples(st.floats(-12, 12), st.floats(-12, 12), st.floats(-2, 2)), min_size=m - 1,
                          max_size=m - 1))
    wps = np.concatenate([[[0.0, 0.0, 0.0]], np.cumsum(np.array(steps), axis=0)])
    if np.any(np.linalg.norm(np.diff(wps, axis=0), axis=1) < 0.5):
        wps = wps + np.arange(m)[:, None] * np.array([0.7, 0.3, 0.0])
    return wps, draw(st.floats(1.0, 6.0)), draw(st.floats(1.0, 5.0))


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(_scenes())
def test_norm_bounded_plans_stay_within_the_norm(scene: tuple[np.ndarray, float, float]) -> None:
    """Random scenes, times from the allocation: the plan holds, and its horizontal speed and
    acceleration by dense sampling never exceed the bounds (the polygon is inside the disc)."""
    wps, vh, ah = scene
    bounds = Bounds.vehicle(horizontal=(vh, ah, 10.0, 40.0), up=(2.0, 1.5, 10.0, 40.0), down=(1.0, 1.5, 10.0, 40.0),
                            z_up=True)
    times = allocate_times(wps, bounds)
    problem = Problem.from_waypoints(wps, np.diff(times), bounds)
    res = plan(problem)
    assert res.ok, res.message
    traj = res.trajectory
    assert _hnorm(traj, 1).max() <= vh * (1 + 1e-9)
    assert _hnorm(traj, 2).max() <= ah * (1 + 1e-9)
    v = traj.evaluate(np.linspace(traj.t0, traj.t_end, DENSE), 1)
    assert v[:, 2].max() <= 2.0 + 1e-9 and v[:, 2].min() >= -1.0 - 1e-9
    rep = verify(traj, replace(problem, times=traj.times))
    assert rep.ok and rep.horizontal_peak is not None and rep.horizontal_peak[0] <= vh


@pytest.mark.parametrize("how", ["compiled", "numpy", "global"])
def test_every_planner_path_respects_the_norm(how: str) -> None:
    sc = load_scenario(json.loads((EXAMPLES / "scenario1.json").read_text()))
    p = sc.problem
    b = Bounds(p.bounds.lo, p.bounds.hi, horizontal=np.array([4.0, 3.0, np.inf, np.inf]))
    problem = replace(p, bounds=b, times=p.times[0] + 0.7 * (p.times - p.times[0]))
    kw = {"method": "global"} if how == "global" else {"options": IterativeOptions(compiled=how == "compiled")}
    res = plan(problem, **kw)  # type: ignore[arg-type]
    assert res.ok, res.message
    peak = _hnorm(res.trajectory, 1).max()
    assert peak <= 4.0 and _hnorm(res.trajectory, 2).max() <= 3.0
    assert peak > 0.9 * 4.0  # the bound binds: the rows were there to be respected
    # the same problem with the box alone flies faster than the norm allows on this scene
    box = plan(replace(problem, bounds=p.bounds), **kw)  # type: ignore[arg-type]
    assert box.ok and _hnorm(box.trajectory, 1).max() > 4.0


def test_local_replan_respects_the_norm() -> None:
    sc = load_scenario(json.loads((EXAMPLES / "scenario1.json").read_text()))
    p = sc.problem
    b = Bounds(p.bounds.lo, p.bounds.hi, horizontal=np.array([4.0, 3.0, np.inf, np.inf]))
    problem = replace(p, bounds=b, times=p.times[0] + 0.7 * (p.times - p.times[0]))
    res = plan(problem)
    assert res.ok
    moved = problem.waypoints[3] + np.array([0.6, -0.5, 0.1])
    rp = replan(problem, res.trajectory, MoveWaypoint(3, moved))
    assert rp.ok, rp.message
    assert verify(rp.trajectory, rp.problem).ok
    assert _hnorm(rp.trajectory, 1).max() <= 4.0 and _hnorm(rp.trajectory, 2).max() <= 3.0


def test_verify_fails_a_plan_over_the_norm() -> None:
    """A plan certified on the per-axis box flies a diagonal above the same number as a norm:
    verify against the norm fails it, names the norm, and reports the peak."""
    wps = np.array([[0.0, 0, 0], [20, 20, 0]])
    box = Bounds.symmetric(4, 3, 10, 40)
    res = plan_mission(wps, box, timing="fastest")
    assert res.ok
    traj = res.trajectory
    assert _hnorm(traj, 1).max() > 4.5  # ~sqrt(2) x 4 allowed by the box
    normed = Bounds(box.lo, box.hi, horizontal=np.array([4.0, 3.0, np.inf, np.inf]))
    rep = verify(traj, replace(res.problem, bounds=normed))
    assert not rep.ok
    assert rep.norm_violation_hull.value > 0 and rep.norm_violation_sampled.value > 0
    assert any(f.startswith("norm_violation_hull") for f in rep.failures())
    assert rep.horizontal_peak is not None and rep.horizontal_peak[0] == pytest.approx(_hnorm(traj, 1).max(), rel=1e-3)
    assert "horizontal_peak" in rep.summary() and json.dumps(rep.to_dict())
    # a plan within the bound passes: the norm check is no blanket refusal
    loose = Bounds(box.lo, box.hi, horizontal=np.array([4.0 * np.sqrt(2) * 1.01, 3.0 * np.sqrt(2) * 1.01, np.inf, np.inf]))
    assert verify(traj, replace(res.problem, bounds=loose)).ok


def test_polygon_costs_at_most_two_percent() -> None:
    """A leg along the polygon's worst direction (an edge's midpoint, 11.25 degrees) planned at the
    fastest the planner certifies flies at over 97 % of the norm bound, and one along an axis
    (a vertex) as fast as the per-axis box of the same number allows."""
    r = 5.0
    for angle, floor in ((np.pi / 16, 0.97), (0.0, 0.97)):
        wps = np.array([[0.0, 0, 0], [60 * np.cos(angle), 60 * np.sin(angle), 0]])
        b = Bounds.vehicle(horizontal=(r, 3.0, 10, 40), up=(2, 2, 10, 40), down=(2, 2, 10, 40), z_up=True)
        res = plan_mission(wps, b, timing="fastest")
        assert res.ok and verify(res.trajectory, res.problem).ok
        peak = _hnorm(res.trajectory, 1).max()
        assert floor * r <= peak <= r
    wps = np.array([[0.0, 0, 0], [60, 0, 0]])
    norm = plan_mission(wps, Bounds.vehicle(horizontal=(r, 3.0, 10, 40), up=(2, 2, 10, 40), down=(2, 2, 10, 40)),
                        timing="fastest")
    box = plan_mission(wps, Bounds(np.array([[-r, -r, -2], [-3, -3, -2], [-10] * 3, [-40] * 3], dtype=float),
                                   np.array([[r, r, 2], [3, 3, 2], [10] * 3, [40] * 3], dtype=float)), timing="fastest")
    assert norm.trajectory.t_end == pytest.approx(box.trajectory.t_end, rel=0.01)


def test_diagonal_legs_are_slower_than_with_the_box() -> None:
    wps = np.array([[0.0, 0, 0], [30, 30, 0], [60, 0, 0]])
    box = Bounds.symmetric(4, 3, 10, 40)
    normed = Bounds(box.lo, box.hi, horizontal=np.array([4.0, 3.0, np.inf, np.inf]))
    fast_box = plan_mission(wps, box, timing="fastest")
    fast_norm = plan_mission(wps, normed, timing="fastest")
    assert fast_box.ok and fast_norm.ok
    assert fast_norm.trajectory.t_end > 1.2 * fast_box.trajectory.t_end
    assert _hnorm(fast_norm.trajectory, 1).max() <= 4.0 < _hnorm(fast_box.trajectory, 1).max()
    # the allocation's directional limit sees the norm through its polygon, exactly
    units = np.array([[1.0, 0, 0], [np.sqrt(0.5), np.sqrt(0.5), 0], [np.cos(np.pi / 16), np.sin(np.pi / 16), 0]])
    lim = directional_bounds(normed, units)
    assert lim[0, 0] == pytest.approx(4.0) and lim[1, 0] == pytest.approx(4.0)
    assert lim[2, 0] == pytest.approx(4.0 * np.cos(np.pi / 16))
    assert directional_bounds(box, units)[1, 0] == pytest.approx(4.0 * np.sqrt(2))


# --- braking ------------------------------------------------------------------------------


def test_braking_respects_the_norm_and_refuses_outside_the_polygon() -> None:
    b = _vehicle(3.0, 2.0)
    jet = np.zeros((5, 3))
    jet[1] = [2.0, 2.0, 0.0]  # |v| 2.83 < 3 * cos(pi / 16) = 2.94
    res = braking_trajectory(jet, b)
    assert res.ok, res.message
    assert _hnorm(res.trajectory, 1).max() <= 3.0 and _hnorm(res.trajectory, 2).max() <= 2.0
    # the stop's time scale sees the horizontal speed at the norm's acceleration
    assert stop_time_scale(jet[1], jet[2], b) == pytest.approx(np.hypot(2, 2) / 2.0)
    # |v| 2.97 at an edge's midpoint (11.25 degrees): inside the disc, outside the certified polygon
    jet[1] = 2.97 * np.array([np.cos(np.pi / 16), np.sin(np.pi / 16), 0.0])
    out = braking_trajectory(jet, b)
    assert not out.ok and "polygon" in out.message and "velocity" in out.message
    jet[1] = 2.97 * np.array([np.sqrt(0.5), np.sqrt(0.5), 0.0])  # the same speed at a vertex (45 degrees)
    assert braking_trajectory(jet, b).ok


# --- formats ------------------------------------------------------------------------------


def test_scenario_format_round_trip_and_frames() -> None:
    sc = json.loads((EXAMPLES / "scenario1.json").read_text())
    sc["bounds"] = {"velocity": {"horizontal": 5, "up": 2.5, "down": 1.5},
                    "acceleration": {"horizontal": 4, "vertical": 1, "box": 3.5}, "jerk": 6, "snap": 15,
                    "polygon_sides": 32}
    b = load_scenario(sc).problem.bounds
    assert np.array_equal(b.horizontal, [5, 4, np.inf, np.inf]) and b.sides == 32
    assert b.hi[0, 2] == 2.5 and b.lo[0, 2] == -1.5  # ENU: up is +z
    assert np.array_equal(b.hi[1], [3.5, 3.5, 1.0]) and np.all(np.isinf(b.hi[0, :2]))
    for frame in ("enu", "ned"):
        sc2 = dict(sc, frame=frame)
        b2 = load_scenario(sc2).problem.bounds
        back = load_scenario(dict(sc2, bounds=bounds_to_dict(b2, frame))).problem.bounds
        assert back.same_as(b2)
    ned = load_scenario(dict(sc, frame="ned")).problem.bounds
    assert ned.lo[0, 2] == -2.5 and ned.hi[0, 2] == 1.5  # NED: up is -z
    box_only = load_scenario(json.loads((EXAMPLES / "scenario1.json").read_text())).problem.bounds
    assert load_scenario(dict(sc, bounds=bounds_to_dict(box_only))).problem.bounds.same_as(box_only)


@pytest.mark.parametrize(
    ("bound", "field", "words"),
    [
        ({"horizontal": 5, "up": 2}, "bounds.velocity.down", "come together"),
        ({"up": 2, "down": 1}, "bounds.velocity.horizontal", "x and y"),
        ({"horizontal": 5}, "bounds.velocity.up", "z needs"),
        ({"horizontal": 0, "vertical": 1}, "bounds.velocity.horizontal", "> 0"),
        ({"horizontal": 5, "vertical": 1, "up": 1, "down": 1}, "bounds.velocity.vertical", "not both"),
        ({"horizontal": 5, "vertical": 1, "speed": 1}, "bounds.velocity.speed", "unknown key"),
        ({"horizontal": 5, "up": 1, "down": 1, "box": [[-1, 1], [-1, 1], [3, 4]]}, "bounds.velocity", "no room"),
    ],
)
def test_scenario_format_errors_name_the_field(bound: dict, field: str, words: str) -> None:
    sc = json.loads((EXAMPLES / "scenario1.json").read_text())
    sc["bounds"] = {"velocity": bound, "acceleration": 3}
    with pytest.raises(ScenarioError) as info:
        load_scenario(sc)
    assert info.value.field == field and words in info.value.reason


def test_mission_message_carries_norm_bounds() -> None:
    from companion.config import Config
    from companion.wire.decode import decode
    from companion.wire.frames import scenario_to_ned
    from companion.wire.messages import MessageError, bounds_from

    msg = {"id": "m", "frame": "enu", "waypoints": [[0, 0, 1], [5, 5, 2]],
           "bounds": {"velocity": {"horizontal": 5, "up": 2.5, "down": 1.5},
                      "acceleration": {"horizontal": 2.5, "vertical": 1.0, "box": [[-2, 2], [-3, 3], [-4, 4]]}}}
    obj = decode("mission", json.dumps(msg).encode(), max_bytes=1 << 20)
    ned = scenario_to_ned(obj)
    b = bounds_from(ned["bounds"], Config())
    assert np.array_equal(b.horizontal[:2], [5, 2.5]) and np.all(np.isinf(b.horizontal[2:]))
    assert b.lo[0, 2] == -2.5 and b.hi[0, 2] == 1.5  # NED: up is -z
    assert np.array_equal(b.lo[1], [-3, -2, -1]) and np.array_equal(b.hi[1], [3, 2, 1])  # box x/y swapped
    with pytest.raises(MessageError) as info:
        decode("mission", json.dumps(dict(msg, bounds={"velocity": {"horizontal": -1}})).encode(), max_bytes=1 << 20)
    assert info.value.field.startswith("bounds.velocity")
    with pytest.raises(MessageError) as info2:
        bounds_from({"velocity": {"horizontal": 5, "up": 1}}, Config())
    assert info2.value.field == "bounds.velocity.down"


def test_scale_search_and_binding_see_the_norm() -> None:
    """Durations too short for a diagonal under the norm: the uniform scale search finds a larger
    scale than under the per-axis box of the same numbers, and names the norm as what binds."""
    from planner_core.feasibility import binding_bound, scale_search

    wps = np.array([[0.0, 0, 0], [20, 20, 0]])
    box = Bounds.symmetric(4, 3, 10, 40)
    normed = Bounds(box.lo, box.hi, horizontal=np.array([4.0, 3.0, np.inf, np.inf]))
    found = {}
    for name, b in (("box", box), ("norm", normed)):
        problem = Problem.from_waypoints(wps, [3.0], b)
        s = scale_search(problem, lambda p: plan(p, diagnose=False))
        assert s.scale is not None and s.result is not None and s.result.ok
        found[name] = (s.scale, s.binding, s.result.trajectory)
    assert found["norm"][0] > 1.3 * found["box"][0]
    binding = found["norm"][1]
    assert binding is not None and binding.side == "norm" and binding.axis is None
    assert "horizontal" in binding.describe() and binding.usage > 0.99
    assert _hnorm(found["norm"][2], 1).max() <= 4.0 and _hnorm(found["norm"][2], 2).max() <= 3.0
    assert binding_bound(found["box"][2], Problem.from_waypoints(wps, [3.0 * found["box"][0]], box)).side in ("max", "min")


def test_compiled_rows_and_checks_agree_with_the_stacked_rows() -> None:
    """With a norm bound, the compiled pass's rows built one at a time (`_materialize`) equal the
    stacked rows, and its check (`_seg_check`, which passes a point inside its polygon's circle
    without evaluating each row) flags exactly the stacked rows outside their limits."""
    from planner_core import window
    from planner_core.window import jet_scales

    if window.kernel_unavailable() is not None:
        pytest.skip(f"compiled pass unavailable: {window.kernel_unavailable()}")
    from planner_core import window_kernel as wk

    rng = np.random.default_rng(3)
    steps = rng.normal(size=(7, 3))
    steps *= 3.0 / np.linalg.norm(steps, axis=1, keepdims=True)
    wps = np.concatenate([np.zeros((1, 3)), np.cumsum(steps, axis=0)])
    eye = np.eye(3)
    cors = tuple(Polytope(np.concatenate([eye, -eye]), np.concatenate([np.maximum(wps[i], wps[i + 1]) + 1,
                                                                      -np.minimum(wps[i], wps[i + 1]) + 1]))
                 for i in range(7))
    b = Bounds.symmetric(7, 6.5, 15, 60)
    normed = Bounds(b.lo, b.hi, horizontal=np.array([2.0, 1.5, 9.0, np.inf]))
    problem = Problem.from_waypoints(wps, np.full(7, 2.5), normed, cors)
    cache = ProblemCache(problem)
    store = window._RowStore(cache, jet_scales(problem.durations), working=True)
    store.hold(0, problem.m - 2)
    c = window._compact_rows(store)
    assert np.any(c.pd == 3)
    pts = np.empty((cache.hull.shape[1] + 10, 3))
    nz = wk.nonzero_runs(cache.hull)
    bad = np.empty(int(np.max(np.diff(store.off))), dtype=np.int64)
    flagged = 0
    for s in range(problem.m - 1):
        n = store.off[s + 1] - store.off[s]
        rows = slice(store.off[s], store.off[s + 1])
        ids = np.arange(n, dtype=np.int64)
        fixed = np.full(n, -1, dtype=np.int64)
        wab, nrm, lim4 = np.empty((n, 24)), np.empty(n), np.empty((4, n))
        wk.materialize(ids, n, store.off[s], np.full(n, s, dtype=np.int64), fixed, fixed, c.off, cache.hull, store.cs,
                        c.pr, c.pd, c.bn1, c.nb, c.face_off, c.pa, problem.waypoints, c.b6, c.f6, np.zeros(24), wab,
                        nrm, lim4)
        np.testing.assert_allclose(wab, store.ab[rows], rtol=1e-14, atol=1e-14)
        np.testing.assert_allclose(lim4[:2], store.lim[:2, rows] - store.c0[rows], rtol=1e-12, atol=1e-12)
        for scale in (0.05, 0.5, 2.0, 10.0):
            xa, xb = scale * rng.normal(size=(4, 3)), scale * rng.normal(size=(4, 3))
            x = np.concatenate([xa.ravel() / store.cs[s], xb.ravel() / store.cs[s + 1]])
            vals = store.c0[rows] + store.ab[rows] @ x
            lim = store.lim[:, rows]
            out = (vals > lim[3]) | (vals < lim[2])
            near = (np.abs(vals - lim[3]) < 1e-9) | (np.abs(vals - lim[2]) < 1e-9)
            nbad = wk.seg_check(s, 0, n, xa, xb, 2, 3, 0.0, cache.hull, c.pr, c.pd, c.bn1, c.nb, c.face_off, c.pa,
                                 problem.waypoints, c.b6, c.f6, nz, pts, bad)
            want = {lr for lr in range(n) if out[lr] and not near[lr]}
            got = set(bad[:nbad].tolist())
            assert want <= got and got - want <= {lr for lr in range(n) if near[lr]}
            f = 6  # faces of every corridor here: bound rows are [0, bn1) and [bn1 + 4 f, nb + 4 f)
            polygon = {lr for lr in want if (lr < c.bn1 and c.pd[lr] == 3)
                       or (c.bn1 + 4 * f <= lr < c.nb + 4 * f and c.pd[lr - 4 * f] == 3)}
            flagged += len(polygon)
    assert flagged > 0  # the random jets did put points outside the polygons


def test_local_qp_names_a_norm_the_fixed_jets_break() -> None:
    """The replan's QP (`localqp.solve_derivatives`): with the neighbours' jets fixed, its
    solution's certified points are inside the polygon; when a fixed jet itself is outside it,
    the failure says so by name instead of a bare "infeasible"."""
    from planner_core.certificate import hull_violation
    from planner_core.localqp import solve_derivatives

    sc = load_scenario(json.loads((EXAMPLES / "scenario1.json").read_text()))
    p = sc.problem
    b = Bounds(p.bounds.lo, p.bounds.hi, horizontal=np.array([4.0, 3.0, np.inf, np.inf]))
    problem = replace(p, bounds=b, times=p.times[0] + 0.7 * (p.times - p.times[0]))
    res = plan(problem)
    assert res.ok
    traj = res.trajectory
    jets = {i: traj.jet(float(t)) for i, t in enumerate(traj.times)}
    durs = {s: float(traj.times[s + 1] - traj.times[s]) for s in range(traj.n_segments)}
    j = 3
    jets[j] = jets[j].copy()
    jets[j][1:] *= 0.5  # a guess only: the free derivatives are solved
    sol = solve_derivatives(jets, durs, b, problem.corridor, [j])
    assert sol.ok, sol.message
    from planner_core.bezier import segment_from_jets

    ctrl = np.stack([segment_from_jets(jets[s] if s != j else sol.jets[j], sol.jets[j] if s + 1 == j else jets[s + 1],
                                       durs[s]) for s in (j - 1, j)])
    assert hull_violation(ctrl, np.array([durs[j - 1], durs[j]]), b, [problem.corridor(j - 1), problem.corridor(j)]) is None
    speed = float(np.hypot(*jets[j - 1][1, :2]))
    assert speed > 0.5
    tight = Bounds(b.lo, b.hi, horizontal=np.array([0.5 * speed, 3.0, np.inf, np.inf]))
    bad = solve_derivatives(jets, durs, tight, problem.corridor, [j])
    assert not bad.ok and "horizontal" in bad.message and "held fixed" in bad.message and f"segment {j - 1}" in bad.message


def test_allocation_is_exact_for_the_polygon() -> None:
    """A straight rest-to-rest leg's shortest certified duration (`takeoff_duration`, which checks
    the allocation against the certificate itself) is longer by exactly 1 / cos(pi / 16) at an
    edge's midpoint than at a vertex (an axis, or 22.5 degrees)."""
    from planner_core import takeoff_duration

    b = Bounds.vehicle(horizontal=(4.0, 3.0, 10, 40), up=(2, 1, 10, 40), down=(1.5, 1, 10, 40))
    at = {a: takeoff_duration(20.0, b, up=(np.cos(a), np.sin(a), 0.0)) for a in (0.0, np.pi / 16, np.pi / 8)}
    assert at[np.pi / 8] == pytest.approx(at[0.0], rel=2e-3)
    assert at[np.pi / 16] == pytest.approx(at[0.0] / np.cos(np.pi / 16), rel=2e-3)


def test_companion_mission_with_vehicle_bounds_flies_within_the_norm() -> None:
    """A mission message with the vehicle form, through the companion's own start of a mission:
    the route's plan holds the norm (dense samples), the vertical up/down limits, and verifies."""
    from companion.config import config_from_dict
    from companion.mission import start_mission
    from companion.wire.messages import mission_from_message
    from planner_core import rest_jet

    cfg = config_from_dict({"planner": {"vehicle_radius": 0.25,
                                        "bounds": {"velocity": 3, "acceleration": 4, "jerk": 20, "snap": 120}}})
    msg = {"id": "m", "waypoints": [[12, 12, -3], [24, 0, -6], [24, 14, -1.5]],
           "bounds": {"velocity": {"horizontal": 2.5, "up": 1.2, "down": 0.8},
                      "acceleration": {"horizontal": 1.5, "vertical": 1.0}}}
    spec = mission_from_message(msg, cfg)
    out = start_mission(spec, rest_jet(np.array([0.0, 0.0, -1.5])), 1.0, [], cfg)
    assert out.ok and out.route is not None, out.message
    traj = out.route.trajectory
    assert verify(traj, out.route.problem).ok
    assert _hnorm(traj, 1).max() <= 2.5 and _hnorm(traj, 2).max() <= 1.5
    # the norm (within the planner's reserve), not the configured box (3 per axis: 4.2 on a
    # diagonal), is what binds
    assert _hnorm(traj, 1).max() > 0.7 * 2.5
    vz = traj.evaluate(np.linspace(traj.t0, traj.t_end, DENSE), 1)[:, 2]
    assert vz.min() >= -1.2 - 1e-9 and vz.max() <= 0.8 + 1e-9  # NED: climbing is -z
