"""The trajectory file's fast writer (issue 25, point 2): on real plans, its text is the same JSON
value as the old writer's (`json.dumps(trajectory_to_dict(...), indent=1)`), reads back to the same
trajectory, and the CLI's files hold it."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from planner_core import Trajectory, plan_mission
from planner_core.formats.io import (
    load_scenario,
    trajectory_from_dict,
    trajectory_json,
    trajectory_to_dict,
)

ROOT = Path(__file__).resolve().parents[2]
EXAMPLES = ROOT / "examples"


def _planned(name: str, timing: str) -> tuple[Trajectory, str, np.ndarray]:
    sc = load_scenario(json.loads((EXAMPLES / name).read_text()))
    p = sc.problem
    mission = plan_mission(p.waypoints, p.bounds, p.corridors, p.durations if timing == "auto" else None,
                           timing=timing, initial=p.initial, final=p.final, t0=float(p.times[0]))
    assert mission.result.ok and mission.result.trajectory is not None
    return mission.result.trajectory, sc.frame, mission.waypoint_index


def _same(a: Trajectory, b: Trajectory) -> None:
    assert np.array_equal(a.times, b.times) and np.array_equal(a.control_points, b.control_points)
    assert (a.corridors is None) == (b.corridors is None)
    for pa, pb in zip(a.corridors or (), b.corridors or (), strict=True):
        assert (pa is None) == (pb is None)
        if pa is not None and pb is not None:
            assert np.array_equal(pa.A, pb.A) and np.array_equal(pa.b, pb.b)
    assert a.stats == b.stats


@pytest.mark.parametrize(("name", "timing"), [("scenario1.json", "auto"), ("scenario2.json", "fastest")])
def test_fast_text_is_the_old_writers_json(name: str, timing: str) -> None:
    traj, frame, index = _planned(name, timing)
    traj = Trajectory(traj.times, traj.control_points, traj.corridors,
                      {**traj.stats, "odd": [float("nan"), np.float64(2.5), (1, 2)], "deep": {"x": {"y": []}}})
    old = json.dumps(trajectory_to_dict(traj, frame, index), indent=1)
    new = trajectory_json(traj, frame, index)
    assert json.loads(new) == json.loads(old)
    assert list(json.loads(new)) == list(json.loads(old))  # the keys in the same order
    _same(trajectory_from_dict(json.loads(new)), trajectory_from_dict(json.loads(old)))
    # one segment a line: a 1000-segment file stays a file of lines, not of numbers
    segments = traj.n_segments
    assert len(new.splitlines()) < len(old.splitlines()) and len(new.splitlines()) >= segments + 6


def test_without_index_or_corridors_and_with_one_segment() -> None:
    traj, frame, _ = _planned("scenario1.json", "auto")
    one = Trajectory(traj.times[:2], traj.control_points[:1], None, {})
    for t, idx in ((traj, None), (one, None), (one, [0, 1])):
        new = trajectory_json(t, frame, idx)
        assert json.loads(new) == json.loads(json.dumps(trajectory_to_dict(t, frame, idx), indent=1))


def test_cli_file_reads_back_as_the_plan(tmp_path: Path) -> None:
    out = tmp_path / "t.json"
    proc = subprocess.run([sys.executable, "-m", "planner_core", "plan", str(EXAMPLES / "scenario1.json"), "-o",
                           str(out), "--json"], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert proc.returncode == 0, proc.stderr
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert summary["write_s"] >= 0.0
    text = out.read_text()
    traj = trajectory_from_dict(json.loads(text))
    assert text == trajectory_json(traj, "enu", json.loads(text).get("waypoint_index"))  # a fixed point
    check = subprocess.run([sys.executable, "-m", "planner_core", "verify", str(EXAMPLES / "scenario1.json"),
                            str(out)], capture_output=True, text=True, cwd=ROOT, timeout=300)
    assert check.returncode == 0, check.stdout + check.stderr
