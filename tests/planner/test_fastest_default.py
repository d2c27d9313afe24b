"""Issue 12, item 2: a mission without durations flies the fastest allocation by default
(`plan_mission`, the scenario loader and the CLI), "timing": "default" keeps the old one, and
knots inserted on long legs never shift the given waypoint indices."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from planner_core import (
    Bounds,
    FieldError,
    MissionPlan,
    Polytope,
    Problem,
    Trajectory,
    allocate_times,
    plan,
    plan_mission,
    verify,
)
from planner_core.allocation import SEARCH_MAX_WAYPOINTS
from planner_core.formats.io import ScenarioError, load_scenario

ROOT = Path(__file__).resolve().parents[2]
DEFAULTS = Bounds.symmetric(3.0, 3.0, 10.0, 50.0)  # companion/config.py [planner.bounds]


def _scene(n_obstacles: int, m: int) -> dict[str, Any]:
    """benchmarks/scale.py's cluttered scene, without its durations."""
    sys.path.insert(0, str(ROOT / "benchmarks"))
    from scale import scene  # type: ignore[import-not-found]

    sc = scene(n_obstacles, m)
    del sc["durations"]
    return dict(sc)


def _dense_peak(traj: Trajectory, problem: Problem) -> float:
    """Largest sampled |derivative| / bound over orders 1..4 (400 samples per segment)."""
    u = (np.arange(400) + 0.5) / 400
    t = (traj.times[:-1, None] + np.diff(traj.times)[:, None] * u[None, :]).ravel()
    sym = np.minimum(problem.bounds.hi, -problem.bounds.lo)
    return max(float(np.max(np.abs(traj.evaluate(t, k)) / sym[k - 1])) for k in range(1, 5))


def _from(problem: Problem, **kw: Any) -> MissionPlan:
    return plan_mission(problem.waypoints, problem.bounds, problem.corridors, initial=problem.initial,
                        final=problem.final, **kw)


@pytest.mark.parametrize(("n_obstacles", "m"), [(10, 10), (50, 100)], ids=["m10-search", "m100-local"])
def test_no_durations_plan_fastest_verified_and_never_slower_than_allocate_times(n_obstacles: int, m: int) -> None:
    scenario = load_scenario(_scene(n_obstacles, m))
    assert scenario.timing == "auto" and not scenario.durations_given
    problem = scenario.problem
    old = plan(problem)  # the loader's times are allocate_times': the old default
    assert np.allclose(problem.times, allocate_times(problem.waypoints, problem.bounds))
    assert old.ok and old.trajectory is not None
    mp = _from(problem)
    assert mp.ok and mp.timing == "fastest" and mp.trajectory is not None
    traj = mp.trajectory
    assert verify(traj, mp.problem).ok
    assert _dense_peak(traj, mp.problem) <= 1.0 + 1e-9
    assert traj.t_end - traj.t0 <= old.trajectory.t_end - old.trajectory.t0 + 1e-9
    alloc = mp.result.stats["allocation"]
    assert alloc["strategy"] == ("search" if mp.problem.m <= SEARCH_MAX_WAYPOINTS else "local")
    assert alloc["waypoint_index"] == mp.waypoint_index.tolist()
    assert np.allclose(traj.waypoints[mp.waypoint_index], problem.waypoints, atol=1e-9)
    # the local pass's own steps are in the planned problem's indices: never reported as stretches
    assert not mp.result.stats.get("stretched_durations") and "duration_scale" not in mp.result.stats


def test_knots_keep_the_given_indices() -> None:
    wps = np.array([[0.0, 0.0, 1.0], [20.0, 0.0, 1.0], [20.0, 2.0, 1.0], [0.0, 2.0, 1.0]])
    eye = np.eye(3)
    box = Polytope(np.concatenate([eye, -eye]), np.array([21.0, 3.0, 2.0, 1.0, 1.0, 0.0]))
    mp = plan_mission(wps, DEFAULTS, (box,) * 3, t0=5.0)
    assert mp.ok and mp.trajectory is not None
    index = mp.waypoint_index
    knots = mp.problem.m - wps.shape[0]
    assert knots > 0  # the two 20 m legs between stops get knots; the 2 m one between them none
    assert index[0] == 0 and index[-1] == mp.problem.m - 1 and np.all(np.diff(index) >= 1)
    assert np.allclose(mp.problem.waypoints[index], wps) and np.allclose(mp.trajectory.waypoints[index], wps)
    assert mp.trajectory.t0 == pytest.approx(5.0)
    source = mp.segment_source
    assert source.shape == (mp.problem.m - 1,) and source[0] == 0 and source[-1] == wps.shape[0] - 2
    for s, j in enumerate(source):  # every planned segment lies on the given segment it maps to
        a, b = wps[j], wps[j + 1]
        for p in mp.problem.waypoints[s : s + 2]:
            assert np.linalg.norm(np.cross(b - a, p - a)) < 1e-9 and -1e-9 <= (p - a) @ (b - a) <= (b - a) @ (b - a) + 1e-9
    assert np.array_equal(np.bincount(source), np.diff(index))
    labels = mp.relabel([7.0, 8.0, 9.0, 10.0])
    assert labels[index].tolist() == [7.0, 8.0, 9.0, 10.0] and int(np.sum(labels == -1.0)) == knots
    with pytest.raises(FieldError, match="labels"):
        mp.relabel([7.0, 8.0])


def test_given_durations_and_the_default_opt_out() -> None:
    wps = np.array([[0.0, 0.0, 1.0], [4.0, 1.0, 1.0], [8.0, 0.0, 1.5]])
    given = plan_mission(wps, DEFAULTS, durations=[6.0, 7.0])
    assert given.ok and given.timing == "given" and given.durations.tolist() == [6.0, 7.0]
    default = plan_mission(wps, DEFAULTS, timing="default")
    assert default.ok and default.timing == "default"
    assert np.allclose(default.problem.times, allocate_times(wps, DEFAULTS))
    fast = plan_mission(wps, DEFAULTS, durations=[6.0, 7.0], timing="fastest")  # the given ones are ignored
    assert fast.ok and fast.timing == "fastest" and fast.trajectory is not None
    assert fast.trajectory.t_end < min(13.0, default.problem.times[-1])


@pytest.mark.parametrize(
    ("kw", "field"),
    [({"timing": "quick"}, "timing"), ({"timing": None}, "timing"), ({"durations": [1.0]}, "durations"),
     ({"durations": [1.0, -2.0]}, "durations[1]"), ({"time_weight": 0.0}, "time_weight"),
     ({"initial": np.zeros((5, 3))}, "initial[0]"), ({"reserve": 1.0}, "reserve"), ({"reserve": -0.1}, "reserve"),
     ({"reserve": float("nan")}, "reserve")],
)
def test_bad_input_names_the_field(kw: dict[str, Any], field: str) -> None:
    with pytest.raises(FieldError) as e:
        plan_mission([[1.0, 0.0, 0.0], [3.0, 0.0, 0.0], [3.0, 2.0, 0.0]], DEFAULTS, **kw)
    assert e.value.field == field


@pytest.mark.parametrize("timing", ["fastest", "default"])
def test_reserve_plans_within_a_share_of_the_bounds_and_keeps_the_full_ones(timing: str) -> None:
    """plan_mission(reserve=r): the flown curve stays within (1 - r) x every bound (dense
    sampling), the planned problem keeps the full bounds (what a replan is checked against) and
    the plan verifies against them; a reserve costs time."""
    wps = [[0.0, 0.0, 1.0], [8.0, 0.0, 1.0], [8.0, 4.0, 2.0], [2.0, 5.0, 1.0]]
    free = plan_mission(wps, DEFAULTS, timing=timing)
    kept = plan_mission(wps, DEFAULTS, timing=timing, reserve=0.25)
    assert free.ok and kept.ok and free.trajectory is not None and kept.trajectory is not None
    traj = kept.trajectory
    assert kept.problem.bounds is DEFAULTS and verify(traj, kept.problem).ok
    ts = np.linspace(traj.t0, traj.t_end, 6000)
    for k in range(1, 5):
        assert np.max(np.abs(traj.evaluate(ts, k)) / DEFAULTS.hi[k - 1]) <= 0.75 * (1 + 1e-6)
    assert traj.t_end - traj.t0 > free.trajectory.t_end - free.trajectory.t0


def test_scenario_timing_values() -> None:
    sc: dict[str, Any] = {"waypoints": [[0, 0, 0], [2, 0, 0]], "bounds": {"velocity": 3, "acceleration": 3}}
    assert load_scenario({**sc, "durations": [3]}).durations_given
    assert load_scenario({**sc, "timing": "default"}).timing == "default"
    for bad in ("Fastest", 1, ["fastest"]):
        with pytest.raises(ScenarioError, match="timing: expected one of 'auto', 'default', 'fastest'") as e:
            load_scenario({**sc, "timing": bad})
        assert e.value.field == "timing"


def test_cli_without_durations_flies_fastest_and_default_opts_out(tmp_path: Path) -> None:
    sc = {"waypoints": [[0, 0, 0], [6, 0, 0], [6, 4, 0]], "bounds": {"velocity": 3, "acceleration": 3, "jerk": 10}}
    path = tmp_path / "s.json"
    out = tmp_path / "t.json"

    def cli(scenario: dict[str, Any], *extra: str) -> tuple[subprocess.CompletedProcess[str], float]:
        path.write_text(json.dumps(scenario))
        r = subprocess.run([sys.executable, "-m", "planner_core", "plan", str(path), "-o", str(out), "--json",
                            *extra], capture_output=True, text=True, cwd=ROOT, timeout=120)
        if r.returncode:
            return r, float("nan")
        segs = json.loads(out.read_text())["segments"]
        return r, segs[-1]["t1"] - segs[0]["t0"]

    r, fastest = cli(sc)
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    assert summary["timing"] == "fastest" and summary["fastest"].startswith("fastest timing: flight")
    r, old = cli({**sc, "timing": "default"})
    assert r.returncode == 0 and json.loads(r.stdout)["timing"] == "default", r.stderr
    r, flag = cli(sc, "--timing", "default")
    assert r.returncode == 0 and flag == pytest.approx(old)
    assert fastest < old
    r, _ = cli({**sc, "timing": "soon"})
    assert r.returncode == 2 and "timing: expected one of" in r.stderr


def test_no_durations_that_cannot_plan_say_why_in_the_given_indices() -> None:
    initial = np.zeros((5, 3))
    initial[1] = [4.0, 0.0, 0.0]  # over the 3 m/s bound at the start: no duration helps
    mp = plan_mission([[0.0, 0.0, 0.0], [20.0, 0.0, 0.0], [20.0, 5.0, 0.0]], DEFAULTS, initial=initial)
    assert not mp.ok and mp.trajectory is None and mp.timing == "fastest"
    d = mp.result.diagnosis
    assert d is not None and d.segment == 0 and "velocity" in mp.message
    assert mp.problem.m == 3 and mp.waypoint_index.tolist() == [0, 1, 2]  # the given problem, no knots
