"""Issue 12: infeasible durations name the bound that binds first and the smallest duration scale
that plans; recovery stretches by that scale and says so."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from planner_core import (
    Bounds,
    PlanStatus,
    Polytope,
    Problem,
    allocate_times,
    fastest_durations,
    plan,
    verify,
)
from planner_core.allocation import insert_knots, knot_pieces
from planner_core.feasibility import binding_bound, scaled
from planner_core.timing import _HULL_C

ROOT = Path(__file__).resolve().parents[2]
DEFAULTS = Bounds.symmetric(3.0, 3.0, 10.0, 50.0)  # companion/config.py [planner.bounds]


def _leg(length: float, duration: float) -> Problem:
    return Problem.from_waypoints([[0.0, 0.0, 1.0], [length, 0.0, 1.0]], [duration], DEFAULTS)


def _mission() -> Problem:
    wps = np.array([[0.0, 0.0, 1.0], [3.0, 1.0, 1.0], [6.0, 0.0, 1.5], [9.0, 2.0, 1.0]])
    eye = np.eye(3)
    box = Polytope(np.concatenate([eye, -eye]), np.array([12.0, 5.0, 4.0, 2.0, 5.0, 1.0]))
    return Problem.from_waypoints(wps, [1.25, 0.3, 1.25], Bounds.symmetric(7.0, 6.5, 15.0, 60.0), (box,) * 3)


@pytest.mark.parametrize("problem", [_leg(30.0, 10.0), _mission()], ids=["leg30m", "mission"])
def test_infeasible_durations_name_binding_bound_and_scale(problem: Problem) -> None:
    res = plan(problem, recover=False)
    assert res.status is PlanStatus.INFEASIBLE and res.diagnosis is not None
    d = res.diagnosis
    assert d.binding is not None and d.min_scale is not None and d.min_scale > 1.0
    b = d.binding
    assert b.kind == "bounds" and b.order in (1, 2, 3, 4) and b.axis in (0, 1, 2)
    assert b.waypoints == (b.segment, b.segment + 1) and b.usage > 0.99
    assert "feasible from duration scale" in res.message and b.describe() in res.message
    assert d.min_durations is not None and np.allclose(d.min_durations, d.min_scale * problem.durations)
    at = plan(scaled(problem, d.min_scale), recover=False)
    assert at.ok
    assert not plan(scaled(problem, 0.9 * d.min_scale), recover=False).ok
    assert at.trajectory is not None
    again = binding_bound(at.trajectory, scaled(problem, d.min_scale))
    assert again is not None and (again.order, again.axis, again.segment) == (b.order, b.axis, b.segment)


# 30 m at 3 m/s in 10 s: the rest-to-rest segment's certificate (3 pieces) needs 2.635 L / v = 26.35 s
LEG_SCALE = float(_HULL_C[0, 0, 0]) * 30.0 / 3.0 / 10.0


def test_single_leg_binding_is_velocity_along_the_leg() -> None:
    d = plan(_leg(30.0, 10.0), recover=False).diagnosis
    assert d is not None and d.binding is not None and d.min_scale is not None
    assert (d.binding.order, d.binding.axis, d.binding.side) == (1, 0, "max")
    assert LEG_SCALE <= d.min_scale <= LEG_SCALE * 1.006
    assert d.waypoint == 1 and d.segment == 0 and "velocity" in d.group


def test_recovery_stretches_uniformly_and_reports() -> None:
    problem = _leg(30.0, 10.0)
    res = plan(problem)  # recover on (default)
    assert res.ok and res.trajectory is not None
    s = res.stats["duration_scale"]
    assert LEG_SCALE <= s <= LEG_SCALE * 1.006
    (c,) = res.stats["stretched_durations"]
    assert c["segment"] == 0 and c["old"] == 10.0 and c["new"] == pytest.approx(10.0 * s)
    assert res.trajectory.t_end == pytest.approx(10.0 * s)
    assert res.stats["scale_search"]["binding"]["order_name"] == "velocity"
    assert "stretching every duration" in res.message


def test_no_scale_helps_says_so() -> None:
    problem = _leg(5.0, 5.0)
    init = problem.initial.copy()
    init[1, 0] = 4.0  # above the 3 m/s bound from the start: no stretch can help
    res = plan(Problem(problem.waypoints, problem.times, DEFAULTS, init, problem.final), recover=False)
    assert not res.ok and res.diagnosis is not None
    assert res.diagnosis.min_scale is None and res.diagnosis.max_scale_tried is not None
    assert "no uniform duration stretch" in res.message


def test_cli_infeasible_leg_prints_binding_and_scale(tmp_path: Path) -> None:
    sc = {"waypoints": [[0, 0, 0], [30, 0, 0]], "durations": [10],
          "bounds": {"velocity": 3, "acceleration": 3, "jerk": 10, "snap": 50}}
    path = tmp_path / "leg.json"
    path.write_text(json.dumps(sc))
    out = tmp_path / "t.json"

    def cli(*extra: str) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "planner_core", "plan", str(path), "-o", str(out), *extra],
                              capture_output=True, text=True, cwd=ROOT, timeout=120)

    r = cli("--no-recover")
    assert r.returncode == 3, r.stderr
    assert "feasible from duration scale 2.6" in r.stderr
    assert "velocity max on axis x in segment 0 (waypoint 0 -> 1) binds first" in r.stderr
    diag = json.loads(r.stderr.strip().splitlines()[-1])["diagnosis"]
    assert diag["binding"]["order_name"] == "velocity" and diag["min_scale"] >= LEG_SCALE
    r = cli()
    assert r.returncode == 0, r.stderr
    assert "stretching every duration by 2.6" in r.stdout and "10 -> 26.3" in r.stdout


# --- minimum-time allocation (planner_core.allocation) -------------------------------------------


def _dense_peak(traj: object, problem: Problem) -> float:
    """Largest sampled |derivative| / bound over orders 1..4 (2000 samples per segment)."""
    from planner_core import Trajectory

    assert isinstance(traj, Trajectory)
    u = (np.arange(2000) + 0.5) / 2000
    d = np.diff(traj.times)
    t = (traj.times[:-1, None] + d[:, None] * u[None, :]).ravel()
    sym = np.minimum(problem.bounds.hi, -problem.bounds.lo)
    return max(float(np.max(np.abs(traj.evaluate(t, k)) / sym[k - 1])) for k in range(1, 5))


def _cluttered(seed: int) -> Problem:
    from dataclasses import replace

    sys.path.insert(0, str(ROOT / "benchmarks"))
    from quality import random_scenario  # type: ignore[import-not-found]

    p = random_scenario(seed).problem
    b = Bounds.symmetric(5.0, 5.0, 15.0, 60.0)
    return replace(p, bounds=b, times=allocate_times(p.waypoints, b, corridors=p.corridors))


@pytest.mark.parametrize("which", ["leg5", "leg20", "mission0", "mission3"])
def test_fastest_allocation_is_verified_never_over_a_bound_and_never_slower(which: str) -> None:
    if which.startswith("leg"):
        length = float(which[3:])
        wps = np.array([[0.0, 0.0, 0.0], [length, 0.0, 0.0]])
        problem = Problem.from_waypoints(wps, np.diff(allocate_times(wps, DEFAULTS)), DEFAULTS)
    else:
        problem = _cluttered(int(which[7:]))
    default = plan(problem)  # the default allocation (what a scenario without times gets)
    assert default.ok and default.trajectory is not None
    fast = fastest_durations(problem)
    assert fast.ok and fast.result.trajectory is not None
    traj = fast.result.trajectory
    assert verify(traj, fast.problem).ok
    assert _dense_peak(traj, fast.problem) <= 1.0 + 1e-9
    assert traj.t_end - traj.t0 <= default.trajectory.t_end - default.trajectory.t0 + 1e-12
    # every given waypoint is passed, at its index in the knotted problem
    assert np.allclose(fast.problem.waypoints[fast.waypoint_index], problem.waypoints)
    assert np.allclose(traj.waypoints[fast.waypoint_index], problem.waypoints, atol=1e-9)
    assert fast.result.stats["allocation"]["plans"] == fast.plans
    if which == "leg20":  # knots: far below the single-segment hull minimum 9 L / v = 60 s
        assert traj.t_end < 0.25 * 60.0


def test_knots_lie_on_the_segment_inside_its_corridor() -> None:
    problem = _mission()
    pieces = np.array([3, 1, 2])
    knotted, index = insert_knots(problem, pieces)
    assert knotted.m == 7 and index.tolist() == [0, 3, 4, 6]
    assert np.allclose(knotted.durations.sum(), problem.durations.sum())
    assert knotted.corridors is not None and problem.corridors is not None
    for j, poly in enumerate(knotted.corridors):
        assert poly is not None and poly.contains(knotted.waypoints[j : j + 2]).all()
    long = Problem.from_waypoints([[0.0, 0.0, 0.0], [50.0, 0.0, 0.0]], [100.0], DEFAULTS)
    assert knot_pieces(long).tolist() == [12]
    assert knot_pieces(_leg(1.0, 5.0)).tolist() == [2]  # rest-to-rest: 0.18 v^2 / a is enough
    assert knot_pieces(_leg(0.5, 5.0)).tolist() == [1]
    assert knot_pieces(_mission()).tolist() == [1, 1, 1]  # short legs between turns: none


def test_fallback_off_is_the_compiled_pass_alone() -> None:
    from planner_core import IterativeOptions
    from planner_core.window import kernel_unavailable

    problem = _cluttered(1)
    a, b = plan(problem), plan(problem, options=IterativeOptions(fallback=False))
    assert a.ok and b.ok and a.trajectory is not None and b.trajectory is not None
    if a.stats["n_compiled_steps"] == problem.m - 2:  # nothing left to the general path: same plan
        assert np.array_equal(a.trajectory.control_points, b.trajectory.control_points)
    fast = scaled(problem, 0.3)
    c = plan(fast, options=IterativeOptions(fallback=False, recover=False, diagnose=False))
    assert not c.ok
    if kernel_unavailable() is None:
        assert "fallback off" in c.message


# --- subdivided hodograph hulls (the tighter certificate's building block) ----------------------


def test_subdivision_pieces_reproduce_the_curve() -> None:
    from planner_core.bezier import evaluate_segment, subdivision_matrix

    rng = np.random.default_rng(3)
    ctrl = rng.normal(size=(10, 3))
    v = np.linspace(0.0, 1.0, 7)
    for p in (1, 2, 3, 4):
        m = subdivision_matrix(9, p)
        assert np.allclose(m.sum(axis=2), 1.0)
        for i in range(p):
            piece = evaluate_segment(m[i] @ ctrl, 1.0, v)
            assert np.allclose(piece, evaluate_segment(ctrl, 1.0, (i + v) / p), atol=1e-12)


def test_subdivided_hull_is_exact_and_nested() -> None:
    from planner_core.bezier import evaluate_segment, subdivided_hull_extent

    rng = np.random.default_rng(4)
    ctrl = rng.normal(size=(20, 10, 3))
    d = rng.uniform(0.5, 2.0, size=20)
    u = np.linspace(0.0, 1.0, 4001)
    for k in range(1, 5):
        ext = {p: subdivided_hull_extent(ctrl, k, d, p) for p in (1, 2, 4, 8)}
        for s in range(20):
            vals = evaluate_segment(ctrl[s], float(d[s]), u, k)
            for p, e in ext.items():  # sampled extremes never leave the certificate
                assert np.all(vals.min(axis=0) >= e[s, 0] - 1e-9) and np.all(vals.max(axis=0) <= e[s, 1] + 1e-9), p
        for a, b in ((1, 2), (2, 4), (4, 8)):  # halving pieces only tightens it
            assert np.all(ext[b][:, 0] >= ext[a][:, 0] - 1e-9) and np.all(ext[b][:, 1] <= ext[a][:, 1] + 1e-9)


def test_subdivided_hull_conservatism_on_the_rest_to_rest_segment() -> None:
    from planner_core.bezier import evaluate_segment, segment_from_jets, subdivided_hull_extent
    from planner_core.problem import rest_jet

    ctrl = segment_from_jets(rest_jet(np.zeros(3)), rest_jet(np.array([1.0, 0.0, 0.0])), 1.0)[None]
    u = np.linspace(0.0, 1.0, 20001)
    # certificate / true peak, orders 1..4 (measured; README "Certificates")
    expected = {1: (3.657, 1.0, 1.0), 2: (7.682, 1.440, 1.069), 3: (12.80, 1.600, 1.0), 4: (14.57, 2.429, 1.214)}
    for k in range(1, 5):
        true = float(np.abs(evaluate_segment(ctrl[0], 1.0, u, k)[:, 0]).max())
        for p, want in zip((1, 2, 4), expected[k], strict=True):
            e = subdivided_hull_extent(ctrl, k, np.ones(1), p)
            ratio = max(-e[0, 0, 0], e[0, 1, 0]) / true
            assert 1.0 - 1e-6 <= ratio <= want * (1 + 2e-3), (k, p)  # exact, and within what we report


def test_cli_timing_fastest_plans_faster_and_verifies(tmp_path: Path) -> None:
    sc = {"waypoints": [[0, 0, 0], [20, 0, 0]], "timing": "fastest",
          "bounds": {"velocity": 3, "acceleration": 3, "jerk": 10, "snap": 50}}
    path = tmp_path / "leg.json"
    path.write_text(json.dumps(sc))
    out = tmp_path / "t.json"
    run = [sys.executable, "-m", "planner_core"]
    r = subprocess.run([*run, "plan", str(path), "-o", str(out)], capture_output=True, text=True, cwd=ROOT,
                       timeout=120)
    assert r.returncode == 0, r.stderr
    assert "fastest timing: flight" in r.stdout
    traj = json.loads(out.read_text())
    flight = traj["segments"][-1]["t1"] - traj["segments"][0]["t0"]
    assert flight < 0.25 * 60.0  # the one-segment hull minimum is 9 L / v = 60 s
    r = subprocess.run([*run, "verify", str(path), str(out)], capture_output=True, text=True, cwd=ROOT, timeout=120)
    assert r.returncode == 0 and "verify: OK" in r.stdout, r.stdout + r.stderr


def test_scenario_timing_is_validated() -> None:
    from planner_core.formats.io import ScenarioError, load_scenario

    sc = {"waypoints": [[0, 0, 0], [2, 0, 0]], "bounds": {"velocity": 3, "acceleration": 3}}
    assert load_scenario(sc).timing == "auto"
    assert load_scenario({**sc, "timing": "fastest"}).timing == "fastest"
    with pytest.raises(ScenarioError, match="timing"):
        load_scenario({**sc, "timing": "quick"})


def test_verify_with_pieces_certifies_what_one_piece_cannot() -> None:
    from planner_core import Trajectory
    from planner_core.bezier import segment_from_jets
    from planner_core.constraints import HULL_PIECES
    from planner_core.problem import rest_jet

    # 20 m rest-to-rest in 20 s: true peak speed 2.46 m/s, the one-piece hull certifies 9 m/s
    ctrl = segment_from_jets(rest_jet(np.zeros(3)), rest_jet(np.array([20.0, 0.0, 0.0])), 20.0)[None]
    traj = Trajectory(np.array([0.0, 20.0]), ctrl)
    problem = Problem.from_waypoints([[0.0, 0.0, 0.0], [20.0, 0.0, 0.0]], [20.0], Bounds.symmetric(3.0, 10, 100, 1e3))
    one, four = verify(traj, problem, pieces=1), verify(traj, problem, pieces=4)
    assert not one.ok and one.bound_violation_hull.order == 1 and one.bound_violation_hull.value > 5.0
    assert four.ok and four.bound_violation_sampled.value <= four.bound_violation_hull.value + 1e-12
    assert four.bound_violation_hull.value == pytest.approx(2.461 - 3.0, abs=2e-3)
    assert verify(traj, problem).ok  # the default is the planner's own pieces
    three = Problem.from_waypoints([[0.0, 0.0, 0.0], [3.0, 1.0, 0.0], [6.0, 0.0, 1.0]], [3.0, 3.0], DEFAULTS)
    res = plan(three)
    assert res.ok and res.trajectory is not None  # planned on HULL_PIECES pieces: more pieces only tighten
    own, more = verify(res.trajectory, three, pieces=HULL_PIECES), verify(res.trajectory, three, pieces=4 * HULL_PIECES)
    assert own.ok and more.ok and more.bound_violation_hull.value <= own.bound_violation_hull.value + 1e-12
