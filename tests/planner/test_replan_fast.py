"""The latency-oriented local replan path: cached QP structure, batched certificate.

Everything runs real QPs (daqp). The properties: the fast QP is the same QP as
the general jet solver; its two corridor assemblies (batched, per segment)
agree; caches keyed on durations never leak between bounds or change results;
the batched certificate fails exactly when it must and names what failed;
rows held by fixed jets are named; a large mission keeps every untouched
segment bit-identical and the input problem untouched.
"""

from __future__ import annotations

import itertools
from dataclasses import replace

import numpy as np
import pytest

from planner_core import certificate, localqp_structure
from planner_core.certificate import certify_rebuilt, hull_violation
from planner_core.changes import ChangeSet, MoveWaypoint, SetCorridor, box
from planner_core.constraints import certified_points
from planner_core.jets import solve_jets
from planner_core.localqp import solve_derivatives
from planner_core.planning import plan
from planner_core.problem import Bounds, Polytope, Problem, Trajectory
from planner_core.replan import Environment, ReplanOptions, jets_of, replan
from planner_core.result import PlanStatus
from tests.planner.test_replan import _ok

OFFSET = np.array([0.3, -0.2, 0.1])


def _mission(m: int, seed: int) -> Problem:
    rng = np.random.default_rng(seed)
    steps = rng.uniform([2.0, -3.0, -0.5], [5.0, 3.0, 0.5], size=(m - 1, 3))
    wps = np.vstack([np.zeros(3), np.cumsum(steps, axis=0)])
    corridors = tuple(box(np.minimum(a, b) - 2.0, np.maximum(a, b) + 2.0) for a, b in itertools.pairwise(wps))
    return Problem.from_waypoints(wps, rng.uniform(1.8, 2.6, m - 1), Bounds.symmetric(7.0, 6.5, 40.0, 400.0), corridors)


def _planned(m: int, seed: int) -> tuple[Problem, Trajectory]:
    problem = _mission(m, seed=seed)
    res = plan(problem)
    assert res.ok and res.trajectory is not None, res.message
    return replace(problem, times=res.trajectory.times.copy()), res.trajectory


@pytest.fixture(scope="module")
def planned() -> tuple[Problem, Trajectory]:
    return _planned(12, seed=4)


@pytest.fixture(scope="module")
def planned_large() -> tuple[Problem, Trajectory]:
    return _planned(80, seed=5)


def _local_qp(
    problem: Problem, traj: Trajectory, j: int, corridors: tuple[Polytope | None, ...] | None = None
) -> tuple[dict[int, np.ndarray], dict[int, float], tuple[Polytope | None, ...]]:
    jets = jets_of(traj)
    local = {i: jets[i].copy() for i in (j - 1, j, j + 1)}
    local[j][0] += OFFSET
    d = np.diff(traj.times)
    corr = problem.corridors if corridors is None else corridors
    assert corr is not None
    return local, {j - 1: float(d[j - 1]), j: float(d[j])}, corr


def test_fast_qp_is_the_general_jet_solvers_qp(planned) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned
    # next to the mission's ends the two differ by ~1e-5 (as before the fast path existed):
    # compare the waypoints whose neighbours are both interior
    for j in range(2, problem.m - 2):
        jets, durations, corr = _local_qp(problem, traj, j)
        fast = solve_derivatives(jets, durations, problem.bounds, lambda s, c=corr: c[s], [j])
        sub = Problem(
            np.array([jets[i][0] for i in (j - 1, j, j + 1)]), traj.times[j - 1 : j + 2].copy(), problem.bounds,
            jets[j - 1], jets[j + 1], corr[j - 1 : j + 1],
        )
        general = solve_jets(sub, np.stack([jets[j - 1], jets[j], jets[j + 1]]), [1])
        assert fast.ok == general.ok, (j, fast.message)
        if fast.ok:
            err = np.abs(fast.jets[j] - general.jets[1]).max() / (1.0 + np.abs(general.jets[1]).max())
            assert err < 1e-9, (j, err)


def test_batched_and_per_segment_corridor_rows_agree(planned) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned
    assert problem.corridors is not None
    j = 5
    jets, durations, corr = _local_qp(problem, traj, j)
    # a far-away extra face on one corridor: the same feasible set, but unequal face counts
    # send the assembly through the per-segment path
    far = corr[j]
    assert far is not None
    extra = Polytope(np.vstack([far.A, [0.0, 0.0, 1.0]]), np.append(far.b, 1e3))
    uneven = (*corr[:j], extra, *corr[j + 1 :])
    a = solve_derivatives(jets, durations, problem.bounds, lambda s: corr[s], [j])
    b = solve_derivatives(jets, durations, problem.bounds, lambda s: uneven[s], [j])
    assert a.ok and b.ok and b.n_rows > a.n_rows
    assert np.allclose(a.jets[j], b.jets[j], rtol=1e-9, atol=1e-9)
    # two free neighbours: a segment with both sides free, also the per-segment path
    d = np.diff(traj.times)
    all_jets = jets_of(traj)
    pair = {i: all_jets[i].copy() for i in range(j - 1, j + 3)}
    pair[j][0] += OFFSET
    two = solve_derivatives(pair, {s: float(d[s]) for s in range(j - 1, j + 2)}, problem.bounds, lambda s: corr[s], [j, j + 1])
    assert two.ok, two.message
    assert set(two.jets) == {j, j + 1}


def test_cached_structures_are_keyed_on_bounds(planned) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned
    j = 6
    move = MoveWaypoint(j, problem.waypoints[j] + OFFSET)
    first = _ok(replan(problem, traj, move))
    tight = replace(problem, bounds=problem.bounds.scaled(0.2))
    tight_res = replan(tight, traj, move, options=ReplanOptions(max_widen=0, max_stretch=0))
    assert tight_res.status is PlanStatus.INFEASIBLE  # same durations, other bounds: not the cached answer
    again = _ok(replan(problem, traj, move))
    assert np.array_equal(again.control_points, first.control_points)


def test_cold_caches_give_the_same_trajectory(planned) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned
    j = 4
    move = MoveWaypoint(j, problem.waypoints[j] + OFFSET)
    warm = _ok(replan(problem, traj, move))
    for module, name in ((certificate, "_cert_map"), (certificate, "_ctrl_map"), (localqp_structure, "segment_mats"),
                         (localqp_structure, "qp_structure"), (localqp_structure, "qp_pattern"),
                         (localqp_structure, "bound_limits")):
        getattr(module, name).cache_clear()
    cold = _ok(replan(problem, traj, move))
    assert np.array_equal(cold.control_points, warm.control_points)


def test_certificate_fails_exactly_when_it_must(planned) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned
    j = 5
    res = replan(problem, traj, MoveWaypoint(j, problem.waypoints[j] + OFFSET))
    new = _ok(res)
    ctrl, times, corr = new.control_points, new.times, new.corridors
    rebuild = [j - 1, j]
    args = (problem.bounds, corr, problem.initial, problem.final)
    assert certify_rebuilt(ctrl, times, rebuild, *args) is None
    # tighter bounds: the same message as the per-segment hull check names
    d = np.diff(times)
    sym = np.minimum(problem.bounds.hi, -problem.bounds.lo)
    used = max(float(np.abs(certified_points(ctrl[rebuild], k, d[rebuild])).max() / sym[k - 1].min())
               for k in range(1, 5))
    tight = problem.bounds.scaled(0.5 * used)  # half of what the certificate uses
    msg = certify_rebuilt(ctrl, times, rebuild, tight, corr, problem.initial, problem.final)
    assert msg is not None and msg == hull_violation(ctrl[rebuild], d[rebuild], tight, [corr[s] for s in rebuild], labels=rebuild)
    # a control point nudged along the curve's own chord: hull still fine, C^4 joint broken
    bent = ctrl.copy()
    bent[j, 1] += 1e-3 * (bent[j, 2] - bent[j, 1])
    msg = certify_rebuilt(bent, times, rebuild, *args)
    assert msg is not None and msg.startswith(f"continuity broken at waypoint {j}")
    # a kept neighbour that no longer joins: caught at the rebuilt segment's far end
    shifted = ctrl.copy()
    shifted[j + 1, :2] += 1e-4
    msg = certify_rebuilt(shifted, times, rebuild, *args)
    assert msg is not None and f"waypoint {j + 1}" in msg
    # NaN never passes
    nan = ctrl.copy()
    nan[j - 1, 4, 2] = np.nan
    assert certify_rebuilt(nan, times, rebuild, *args) is not None
    # a corridor that the rebuilt segment leaves
    assert corr is not None
    moved = list(corr)
    moved[j] = Polytope(corr[j].A, corr[j].b - 10.0)  # type: ignore[union-attr]
    msg = certify_rebuilt(ctrl, times, rebuild, problem.bounds, tuple(moved), problem.initial, problem.final)
    assert msg is not None and msg.startswith("corridor violated") and msg.endswith(f"segment {j}")


def test_rows_held_by_fixed_jets_are_named(planned) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned
    j = 5
    jets, durations, corr = _local_qp(problem, traj, j)
    jets[j - 1][2] += 50.0  # the fixed neighbour's acceleration far beyond 6.5 m/s^2
    sol = solve_derivatives(jets, durations, problem.bounds, lambda s: corr[s], [j])
    assert not sol.ok
    assert f"of segment {j - 1}" in sol.message and "held fixed" in sol.message
    jets, durations, corr = _local_qp(problem, traj, j)
    cut = list(corr)
    poly = corr[j]
    assert poly is not None
    # the corridor of segment j no longer holds the fixed end of that segment (P^5..P^8 come from jet j+1)
    p9 = jets[j + 1][0]
    cut[j] = Polytope(np.vstack([poly.A, -(p9 - jets[j][0])]), np.append(poly.b, -(p9 - jets[j][0]) @ p9 - 0.5))
    sol = solve_derivatives(jets, durations, problem.bounds, lambda s: cut[s], [j])
    assert not sol.ok and sol.message.startswith(f"corridor of segment {j}") and "held fixed" in sol.message


def test_waypoint_outside_its_corridor_is_named(planned) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned
    j = 6
    res = replan(problem, traj, MoveWaypoint(j, problem.waypoints[j] + np.array([0.0, 0.0, 30.0])))
    assert res.status is PlanStatus.INFEASIBLE and res.trajectory is None
    assert res.message.startswith(f"waypoint {j} at") and "outside the corridor" in res.message
    assert res.diagnosis is not None and res.diagnosis["kind"] == "corridor" and res.diagnosis["waypoint"] == j


def test_large_mission_keeps_everything_untouched(planned_large) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned_large
    before_wps = problem.waypoints.copy()
    before_corr = problem.corridors
    assert before_corr is not None
    for j in (1, 40, problem.m - 2):
        res = replan(problem, traj, MoveWaypoint(j, problem.waypoints[j] + OFFSET))
        new = _ok(res)
        changed = {s for s in range(traj.n_segments) if not np.array_equal(new.control_points[s], traj.control_points[s])}
        assert changed <= {j - 1, j} and changed, (j, changed)
        assert res.problem.corridors is not None
        assert all(a is b for a, b in zip(res.problem.corridors, before_corr, strict=True))
    # a corridor change writes to the working copy only
    s = 30
    tight = box(traj.control_points[s].min(axis=0) - 0.05, traj.control_points[s].max(axis=0) + 0.05)
    res = replan(problem, traj, SetCorridor(s, tight))
    _ok(res)
    assert res.problem.corridors is not None and res.problem.corridors[s] is tight
    assert problem.corridors is before_corr and problem.corridors[s] is not tight
    assert np.array_equal(problem.waypoints, before_wps)


def test_split_with_environment_keeps_the_flown_piece(planned_large) -> None:  # type: ignore[no-untyped-def]
    problem, traj = planned_large
    wps = problem.waypoints
    env = Environment((), (wps.min(axis=0) - 10.0, wps.max(axis=0) + 10.0), 0.3)
    for j in (5, 41):
        t = float(traj.times[j - 1]) + 0.37
        change = ChangeSet((MoveWaypoint(j, wps[j] + OFFSET),), from_time=t)
        res = replan(problem, traj, change, options=ReplanOptions(environment=env))
        new = _ok(res)
        assert res.stats["split_index"] == j
        ts = np.linspace(traj.t0, t, 200)
        assert np.max(np.abs(new.evaluate(ts) - traj.evaluate(ts))) <= 1e-9
        assert np.allclose(new.evaluate(new.times[j + 1]), wps[j] + OFFSET, atol=1e-12)
        # every segment after the moved waypoint's two is bit-identical to before the split
        assert all(np.array_equal(new.control_points[s + 1], traj.control_points[s]) for s in range(j + 1, traj.n_segments))
