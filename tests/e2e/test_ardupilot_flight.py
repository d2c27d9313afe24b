"""ArduPilot flavour: GUIDED, arm, NAV_TAKEOFF, then a streamed mission and a pilot takeover."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from typing import Any

import numpy as np
import pytest
from e2e_rig import (
    RADIUS,
    REPO,
    TRACKING_ALLOWANCE,
    Rig,
    arrival_gap,
    box,
    inside,
    polytope,
    setpoints,
    states,
    stream_problem,
    tracking_allowance,
    tracking_rms,
)

from planner_core.formats.io import trajectory_from_dict

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def rig(rig_factory: Any) -> Rig:
    r: Rig = rig_factory("ardupilot")
    r.ensure_airborne()
    return r


def test_takeoff_uses_guided_and_nav_takeoff(rig: Rig) -> None:
    st = rig.control.state()
    assert st["mode"] == "GUIDED" and st["armed"]
    assert st["position"][2] == pytest.approx(-1.0, abs=0.2)
    log = rig.log()
    commands = [r["command"] for r in log if r["type"] == "event" and r.get("event") == "command"]
    assert 22 in commands  # MAV_CMD_NAV_TAKEOFF
    assert rig.statuses[-1]["autopilot"] == "ardupilot"


def test_mission_ardupilot(rig: Rig) -> None:
    obstacle = box([0.7, 0.7, -3.0], [1.3, 1.3, 0.0])
    mission = {"id": "apm-square", "frame": "enu", "obstacles": [
        # the same box in ENU: x and y swap, z flips (it spans z 0..3 up)
        {"A": box([0.7, 0.7, 0.0], [1.3, 1.3, 3.0])["A"], "b": box([0.7, 0.7, 0.0], [1.3, 1.3, 3.0])["b"]}],
        # ENU waypoints of the NED square (2,0,-1.2) (2,2,-1.2) (0,2,-1.5)
        "waypoints": [[0.0, 2.0, 1.2], [2.0, 2.0, 1.2], [2.0, 0.0, 1.5]]}
    t0, t1, _ = rig.fly(mission)
    log = rig.log()
    assert tracking_rms(log, t0, t1) <= tracking_allowance(log, t0, t1)
    final = np.asarray(rig.control.state()["position"])
    assert np.linalg.norm(final - np.array([0.0, 2.0, -1.5])) <= 0.1
    assert stream_problem(setpoints(log, t0, t1)) is None
    assert arrival_gap(setpoints(log, t0, t1)) <= 0.5
    track = np.array([r["pos"] for r in states(log, t0, t1)])
    assert not np.any(inside(track, polytope(obstacle), RADIUS - TRACKING_ALLOWANCE))
    assert rig.wait_status(lambda s: s["state"] == "HOLDING", 3, "holding")["mode"] == "GUIDED"


def test_change_moves_a_waypoint_in_flight(rig: Rig) -> None:
    since = rig.mark()
    rig.put("mission", {"id": "apm-change", "waypoints": [[2.0, 2.0, -1.5], [2.0, 4.0, -1.5], [0.0, 4.0, -1.5]]})
    rig.wait_event(lambda e: e["type"] == "state" and e.get("to") == "STREAMING", 10, "streaming", since)
    time.sleep(0.3)
    before = rig.latest_trajectory()
    mark = rig.mark()
    rig.put("change", {"move_waypoint": {"index": 2, "position": [0.0, 3.0, -1.2]}})
    ev = rig.wait_event(lambda e: e["type"] in ("replanned", "braking", "rejected"), 10, "replan", mark)
    assert ev["type"] == "replanned", ev
    t_split = ev["split_time"]
    time.sleep(0.2)
    after = rig.latest_trajectory()
    ts = np.linspace(max(before.t0, after.t0), t_split, 100)
    assert np.max(np.abs(before.evaluate(ts) - after.evaluate(ts))) <= 1e-9
    assert np.allclose(after.evaluate(after.t_end), [0.0, 3.0, -1.2], atol=1e-9)
    rig.wait_event(lambda e: e["type"] == "mission_complete" and e.get("mission") == "apm-change", 30, "complete", since)
    time.sleep(0.5)
    assert np.linalg.norm(np.asarray(rig.control.state()["position"]) - [0.0, 3.0, -1.2]) <= 0.1
    mark = rig.mark()
    rig.put("change", {"move_waypoint": {"index": 0, "position": [0.0, 3.0, -1.2]}})
    ev = rig.wait_event(lambda e: e["type"] == "rejected", 5, "passed waypoint rejected", mark)
    assert ev["field"] == "move_waypoint.index"


def test_queryables_and_liveliness(rig: Rig) -> None:
    replies = list(rig.session.get(rig.key("status"), timeout=5.0))
    status = json.loads(replies[0].ok.payload.to_bytes())
    assert status["vehicle"] == "e2e" and status["autopilot"] == "ardupilot"
    replies = list(rig.session.get(rig.key("plan"), timeout=5.0))
    plan = json.loads(replies[0].ok.payload.to_bytes())
    assert plan["format"] == "bezier-trajectory/1" and plan["frame"] == "ned"
    assert trajectory_from_dict(plan).n_segments == len(plan["segments"])
    alive = list(rig.session.liveliness().get(rig.key("alive"), timeout=5.0))
    assert [str(r.ok.key_expr) for r in alive] == [rig.key("alive")]


def test_cli_send_reports_the_rejection(rig: Rig, tmp_path: Any) -> None:
    bad = tmp_path / "bad.json"
    bad.write_text('{"command": "loop"}')
    out = subprocess.run(
        [sys.executable, "-m", "companion", "send", "command", str(bad), "--vehicle", "e2e",
         "--connect", f"tcp/127.0.0.1:{rig.zport}", "--wait", "5"],
        capture_output=True, text=True, timeout=30, cwd=REPO)
    assert out.returncode == 1, out.stderr
    events = [json.loads(line) for line in out.stdout.splitlines()]
    assert any(e["type"] == "rejected" and e["field"] == "command" for e in events)


def test_pilot_takeover_ardupilot(rig: Rig) -> None:
    since = rig.mark()
    rig.put("mission", {"id": "apm-takeover", "waypoints": [[1.5, 2.0, -1.5], [1.5, 0.0, -1.5]]})
    rig.wait_event(lambda e: e["type"] == "state" and e.get("to") == "STREAMING", 10, "streaming", since)
    time.sleep(0.5)
    assert rig.control.set_mode("LOITER")["ok"]
    t_switch = rig.mock_time()
    rig.wait_event(lambda e: e["type"] == "pilot_takeover", 5, "pilot takeover", since)
    rig.wait_status(lambda s: s["state"] == "PILOT" and not s["streaming"], 3, "PILOT")
    time.sleep(1.5)
    assert setpoints(rig.log(), t_switch + 0.5, rig.mock_time()) == []
    assert rig.control.state()["mode"] == "LOITER"
