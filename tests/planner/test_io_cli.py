"""Scenario loading, trajectory JSON, the CLI's exit codes and messages, and a silent OSQP."""

from __future__ import annotations

import copy
import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from planner_core import plan
from planner_core.formats.io import (
    ScenarioError,
    load_scenario,
    trajectory_from_dict,
    trajectory_to_dict,
)
from planner_core.qp import solve_qp

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"


def base() -> dict[str, Any]:
    return {
        "frame": "enu",
        "waypoints": [[0, 0, 1], [3, 1, 1], [6, 0, 1.5], [9, 2, 1]],
        "durations": [2.5, 2.5, 2.5],
        "bounds": {"velocity": 7, "acceleration": 6.5, "jerk": 15, "snap": 60},
        "corridors": [
            {"A": [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
             "b": [a + 1, -b + 1, c + 1, -d + 1, 3, 0]}
            for a, b, c, d in [(3, 0, 1, 0), (6, 3, 1, 0), (9, 6, 2, 0)]
        ],
    }


def run_cli(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(
        [sys.executable, "-m", "planner_core", *args], capture_output=True, text=True, cwd=ROOT, timeout=120
    )


def test_base_is_valid() -> None:
    sc = load_scenario(base())
    assert sc.problem.m == 4 and sc.problem.corridors is not None
    assert plan(sc.problem).ok


def _mut(path: str, value: Any) -> dict[str, Any]:
    d = copy.deepcopy(base())
    obj: Any = d
    keys = path.split(".")
    for k in keys[:-1]:
        obj = obj[int(k)] if k.isdigit() else obj[k]
    last = keys[-1]
    if value is _DELETE:
        del obj[last]
    elif last.isdigit():
        obj[int(last)] = value
    else:
        obj[last] = value
    return d


_DELETE = object()

INVALID = [
    (_mut("extra", 1), "extra"),
    (_mut("bounds.jolt", 3), "bounds.jolt"),
    (_mut("waypoints.2", [6, float("nan"), 1]), "waypoints[2][1]"),
    (_mut("waypoints.1", [3, 1]), "waypoints[1]"),
    (_mut("waypoints.1", [3, float("inf"), 1]), "waypoints[1][1]"),
    (_mut("durations.1", 0.0), "durations[1]"),
    (_mut("durations.1", -2.0), "durations[1]"),
    (_mut("durations", [1.0, 2.0]), "durations"),
    (_mut("times", [0, 1, 2, 3]), "times"),  # both times and durations
    (_mut("bounds.velocity", [3, 2]), "bounds.velocity"),
    (_mut("bounds.acceleration", [[-1, 1], [2, 1], [-1, 1]]), "bounds.acceleration[1]"),
    (_mut("bounds.velocity", "fast"), "bounds.velocity"),
    (_mut("bounds.velocity", _DELETE), "bounds.velocity"),
    (_mut("frame", "xyz"), "frame"),
    (_mut("corridors.1.b", [1, 2]), "corridors[1].b"),
    (_mut("corridors", []), "corridors"),
    (_mut("waypoints.2", [6, 0, 4.5]), "waypoints[2]"),  # outside its corridor
    (_mut("vehicle_radius", -1), "vehicle_radius"),
    (_mut("description", 5), "description"),
    (_mut("map", {"min": [0, 0, 0], "max": [1, 1, 0]}), "map.min[2]"),
    (_mut("initial", {"velocity": [1, 2]}), "initial.velocity"),
]


@pytest.mark.parametrize(("scenario", "field"), INVALID)
def test_loader_names_field(scenario: dict[str, Any], field: str) -> None:
    with pytest.raises(ScenarioError) as e:
        load_scenario(scenario)
    assert e.value.field == field
    assert str(e.value).startswith(field + ":")


def test_non_increasing_times() -> None:
    d = base()
    del d["durations"]
    d["times"] = [0, 2, 2, 5]
    with pytest.raises(ScenarioError, match=r"times\[2\]"):
        load_scenario(d)


def test_bound_message_format() -> None:
    with pytest.raises(ScenarioError, match=r"bounds\.velocity: lo 3 > hi 2"):
        load_scenario(_mut("bounds.velocity", [3, 2]))


def test_bound_forms() -> None:
    d = _mut("bounds.velocity", [[-1, 2], [-3, 4], [-5, 6]])
    d["bounds"]["acceleration"] = [-2, 3]
    b = load_scenario(d).problem.bounds
    assert b.lo[0].tolist() == [-1, -3, -5] and b.hi[0].tolist() == [2, 4, 6]
    assert b.lo[1].tolist() == [-2, -2, -2] and b.hi[1].tolist() == [3, 3, 3]


@pytest.mark.parametrize(("scenario", "field"), INVALID[:4])
def test_cli_invalid_input_exit_2(tmp_path: Path, scenario: dict[str, Any], field: str) -> None:
    path = tmp_path / "s.json"
    path.write_text(json.dumps(scenario).replace("NaN", "NaN"))
    r = run_cli("plan", str(path), "-o", str(tmp_path / "t.json"))
    assert r.returncode == 2, r.stderr
    assert field in r.stderr
    assert not (tmp_path / "t.json").exists()


def test_cli_bad_json_exit_2(tmp_path: Path) -> None:
    path = tmp_path / "s.json"
    path.write_text("{not json")
    r = run_cli("plan", str(path), "-o", str(tmp_path / "t.json"))
    assert r.returncode == 2 and "invalid JSON" in r.stderr


def test_cli_infeasible_exit_3(tmp_path: Path) -> None:
    d = base()
    d["durations"] = [2.5, 0.25, 2.5]  # 3 m in 0.25 s at 7 m/s: impossible
    path = tmp_path / "s.json"
    path.write_text(json.dumps(d))
    r = run_cli("plan", str(path), "-o", str(tmp_path / "t.json"), "--window", "1", "--no-recover")
    assert r.returncode == 3, r.stderr
    assert "waypoint" in r.stderr and "segment 1" in r.stderr
    assert "bounds order" in r.stderr or "corridor" in r.stderr
    diag = json.loads(r.stderr.strip().splitlines()[-1])["diagnosis"]
    assert diag["segment"] == 1 and diag["kind"] in ("bounds", "corridor")


def test_cli_infeasible_initial_state_exit_3(tmp_path: Path) -> None:
    d = base()
    d["initial"] = {"velocity": [9.0, 0.0, 0.0]}  # above the 7 m/s bound: no recovery can help
    path = tmp_path / "s.json"
    path.write_text(json.dumps(d))
    r = run_cli("plan", str(path), "-o", str(tmp_path / "t.json"))
    assert r.returncode == 3, r.stderr
    assert "waypoint 1" in r.stderr and "segment 0" in r.stderr
    assert "bounds order 1 (velocity)" in r.stderr and "initial state" in r.stderr


def test_recovery_stretches_and_reports() -> None:
    d = base()
    d["durations"] = [2.5, 0.25, 2.5]
    sc = load_scenario(d)
    res = plan(sc.problem, window=1)
    assert res.ok and res.trajectory is not None
    changes = res.stats["stretched_durations"]
    assert changes and all(c["new"] > c["old"] for c in changes)
    d_new = np.diff(res.trajectory.times)
    for c in changes:
        assert d_new[c["segment"]] == pytest.approx(c["new"])
    untouched = [s for s in range(3) if s not in {c["segment"] for c in changes}]
    assert np.allclose(d_new[untouched], sc.problem.durations[untouched])


def test_cli_plan_verify_round_trip(tmp_path: Path) -> None:
    out = tmp_path / "t.json"
    r = run_cli("plan", str(EXAMPLES / "scenario2.json"), "-o", str(out), "--method", "global")
    assert r.returncode == 0, r.stderr
    r = run_cli("verify", str(EXAMPLES / "scenario2.json"), str(out))
    assert r.returncode == 0 and "verify: OK" in r.stdout
    # tamper with one control point: verify must fail with exit 1
    d = json.loads(out.read_text())
    d["segments"][3]["control_points"][4][0] += 0.5
    out.write_text(json.dumps(d))
    r = run_cli("verify", str(EXAMPLES / "scenario2.json"), str(out))
    assert r.returncode == 1 and "FAILED" in r.stdout


def test_trajectory_json_round_trip() -> None:
    sc = load_scenario(base())
    res = plan(sc.problem)
    assert res.trajectory is not None
    d = json.loads(json.dumps(trajectory_to_dict(res.trajectory, "enu")))
    assert d["format"] == "bezier-trajectory/1" and d["degree"] == 9
    back = trajectory_from_dict(d)
    assert np.array_equal(back.control_points, res.trajectory.control_points)
    assert np.array_equal(back.times, res.trajectory.times)
    assert back.corridors is not None and len(back.corridors) == 3


def test_trajectory_from_dict_rejects_bad_input() -> None:
    with pytest.raises(ScenarioError, match="format"):
        trajectory_from_dict({"format": "x", "segments": []})
    with pytest.raises(ScenarioError, match=r"segments\[0\]\.control_points"):
        trajectory_from_dict({"format": "bezier-trajectory/1", "segments": [
            {"t0": 0, "t1": 1, "control_points": [[0, 0, 0]] * 9, "corridor": None}]})


def test_osqp_prints_nothing(capfd: pytest.CaptureFixture[str]) -> None:
    sc = load_scenario(base())
    res = plan(sc.problem, "global")
    assert res.ok
    P = np.eye(2)
    # an already-optimal start: the case where OSQP says "Polishing not needed"
    solve_qp(P, np.zeros(2), np.eye(2), np.array([-1.0, -1.0]), np.array([1.0, 1.0]), "osqp")
    out, _ = capfd.readouterr()
    assert out == ""


def test_examples_segments_are_clear_of_obstacles() -> None:
    from planner_core.geometry import polytope_vertices, separation

    for name in ("scenario1.json", "scenario2.json"):
        sc = load_scenario(json.loads((EXAMPLES / name).read_text()))
        w = sc.problem.waypoints
        for j in range(sc.problem.m - 1):
            for k, obs in enumerate(sc.obstacles):
                _, gap = separation(w[j : j + 2], polytope_vertices(obs))
                assert gap > 2 * sc.vehicle_radius, (name, j, k, gap)


def test_example_change_files_parse() -> None:
    popup = json.loads((EXAMPLES / "scenario2_popup.json").read_text())
    assert len(popup["obstacles"]) == 1
    move = json.loads((EXAMPLES / "scenario2_move.json").read_text())
    assert move["move_waypoint"]["index"] == 2


def test_cli_plot(tmp_path: Path) -> None:
    pytest.importorskip("matplotlib")
    prefix = tmp_path / "s1"
    r = run_cli("plan", str(EXAMPLES / "scenario1.json"), "-o", str(tmp_path / "t.json"), "--plot", str(prefix))
    assert r.returncode == 0, r.stderr
    for suffix in ("path2d", "path3d", "derivatives"):
        p = Path(f"{prefix}_{suffix}.png")
        assert p.exists() and p.stat().st_size > 10_000


def test_missing_times_use_allocation() -> None:
    pytest.importorskip("planner_core.timing")
    d = base()
    del d["durations"]
    sc = load_scenario(d)
    t = sc.problem.times
    assert t.shape == (4,) and t[0] == 0.0 and np.all(np.diff(t) > 0)
    assert plan(sc.problem).ok


def test_obstacles_without_corridors_build_corridors() -> None:
    pytest.importorskip("planner_core.geometry")
    sc = load_scenario(json.loads((EXAMPLES / "scenario1.json").read_text()))
    assert "corridors" not in sc.raw
    assert sc.problem.corridors is not None and len(sc.problem.corridors) == sc.problem.m - 1
    assert len(sc.obstacles) == 9


def test_cli_reports_start_up_apart_from_the_plan_and_both_paths_agree(tmp_path: Path) -> None:
    """A small scenario planned as a one-shot process takes the numpy path (loading numba would
    cost more than it saves) unless the AOT build of the compiled pass is there (milliseconds to
    load); `--compiled on` loads the compiled pass, counted as start-up, not
    plan. Both plans verify, and they are the same plan (same QPs, another solver)."""
    scenario = tmp_path / "s.json"
    scenario.write_text(json.dumps(base()))
    runs = {}
    for mode in ("auto", "on"):
        out = tmp_path / f"{mode}.json"
        r = run_cli("plan", str(scenario), "-o", str(out), "--compiled", mode, "--json")
        assert r.returncode == 0, r.stderr
        summary = json.loads(r.stdout)
        start = summary["startup"]
        assert summary["plan_s"] > 0 and start["imports_s"] > 0
        assert start["total_s"] == pytest.approx(start["imports_s"] + start["kernel_load_s"], abs=1e-9)
        # the planner's own clock sits inside the CLI's plan time, which holds none of the start-up
        assert summary["planner_time_s"] <= summary["plan_s"]
        written = json.loads(out.read_text())
        assert written["stats"]["startup"] == start and written["stats"]["plan_s"] == summary["plan_s"]
        runs[mode] = (start, trajectory_from_dict(written))
    from planner_core.window import aot_ready

    if aot_ready():  # the AOT build loads in milliseconds: it pays off at any size
        assert runs["auto"][0]["path"] == "compiled" and runs["auto"][0]["kernel_load_s"] < 0.1
    else:
        assert runs["auto"][0]["path"] == "numpy" and runs["auto"][0]["kernel_load_s"] == 0.0
    assert runs["on"][0]["path"] == "compiled" and runs["on"][0]["kernel_load_s"] > 0
    small, compiled = runs["auto"][1], runs["on"][1]
    problem = load_scenario(base()).problem
    from planner_core import verify

    assert verify(small, problem).ok and verify(compiled, problem).ok
    scale = np.abs(compiled.control_points).max()
    np.testing.assert_allclose(small.control_points, compiled.control_points, atol=1e-8 * scale)
    # the text form says the same, on two lines: the plan, then the start-up
    r = run_cli("plan", str(scenario), "-o", str(tmp_path / "t.json"))
    assert r.returncode == 0, r.stderr
    first, second = r.stdout.strip().splitlines()[-2:]
    assert ("compiled path" if aot_ready() else "numpy path") in first and " plan " in first
    assert second.startswith("start-up ") and "imports" in second and "compiled pass" in second
    if not aot_ready():
        assert "compiled pass 0 ms" in second
