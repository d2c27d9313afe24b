"""Smoke test of `python -m companion demo --quick` (an alias of `python -m demo`): the whole
chain flies one short mission.

Real processes (mock autopilot, companion service), a real Zenoh peer on loopback, real MAVLink
over UDP. The demo itself judges the flight; this test checks its verdict and the numbers behind
it, so a demo that printed OK on a bad flight would fail here too.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


def test_quick_demo_flies_and_reports(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    proc = subprocess.run(
        [sys.executable, "-m", "companion", "demo", "--quick", "--out", str(out), "--timeout", "90"],
        capture_output=True,
        text=True,
        timeout=150,
        cwd=ROOT,
    )
    report = proc.stdout + proc.stderr
    assert proc.returncode == 0, report[-4000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ok"] is True
    (mission,) = summary["missions"]
    assert mission["result"] == "OK"
    assert mission["verified"] == "True"
    rms, worst = (float(x) for x in mission["tracking error RMS / max"].removesuffix(" m").split(" / "))
    assert 0.0 < rms <= worst <= 1.0, report[-2000:]
    # what reached the mock is the planned trajectory, sampled (float32 on the wire)
    assert float(mission["setpoints vs trajectory, max"].removesuffix(" m")) < 1e-3
    for key in ("peak |v| planned / bound", "peak |a| planned / bound"):
        peak, bound = (float(x) for x in mission[key].split(" / "))
        assert 0.0 < peak <= bound
    for png in ("quick_path.png", "quick_derivatives.png"):
        assert (out / png).stat().st_size > 10_000
    log = [json.loads(line) for line in (out / "flight.jsonl").read_text().splitlines() if line.strip()]
    assert any(r["type"] == "setpoint" and r.get("applied") for r in log)
    # the companion's recording of the flight (issue 23), read with the mcap reader
    from mcap.reader import make_reader

    assert "python -m companion recording summary" in proc.stdout
    with open(out / "flight.mcap", "rb") as fh:
        stats = make_reader(fh).get_summary().statistics
        topics = {c.topic: stats.channel_message_counts.get(i, 0) for i, c in make_reader(fh).get_summary().channels.items()}
    applied = sum(1 for r in log if r["type"] == "setpoint")
    assert topics["/mavlink/out/SET_POSITION_TARGET_LOCAL_NED"] >= applied > 0
    assert topics["/planner/plan"] >= 2 and topics["/viz/planned_path"] >= 1


def test_demo_scenarios_are_flyable_after_lifting_and_moving() -> None:
    """The demo's adaptations of the paper's scenario 2: lifted 2 m, waypoint 2 moved, pop-up
    obstacle shifted clear of the leg. Corridors must exist for the whole route, the shifted
    obstacle must still cut the originally planned curve, and lifting must keep every obstacle
    where it was relative to the waypoints."""
    import numpy as np

    from demo import run as demo
    from planner_core import plan
    from planner_core.geometry import CorridorError, build_corridors
    from planner_core.problem import Bounds, Polytope, Problem

    raw = demo.load_example("scenario2.json")
    mission = demo.lifted_mission(raw, "s2")
    from companion.config import tracking_allowance
    from demo.rig import demo_config

    # the companion inflates obstacles by the radius plus its tracking allowance
    allowance = tracking_allowance(demo_config(7447, 14540).planner, "px4")[0]
    assert allowance > 0.0
    popup = demo.lifted_obstacles(demo.clear_of_route(demo.load_example("scenario2_popup.json"), mission, allowance))
    original = demo.lifted_obstacles(demo.load_example("scenario2_popup.json"))
    change = demo.lifted_change(demo.load_example("scenario2_move.json"))

    def polys(regions: list[dict[str, object]]) -> list[Polytope]:
        return [Polytope(np.asarray(r["A"], float), np.asarray(r["b"], float)) for r in regions]

    wps = np.asarray(mission["waypoints"], float)
    assert np.allclose(wps - np.asarray(raw["waypoints"], float), [0, 0, demo.LIFT])
    obstacles = polys(mission["obstacles"])
    up = np.array([0.0, 0.0, demo.LIFT])
    for lifted, region in zip(obstacles, raw["obstacles"], strict=True):
        b = np.asarray(region["b"], float)  # boxes: A = [I; -I], b = [max; -min]
        centre = (b[:3] - b[3:]) / 2
        assert lifted.contains(centre + up)[0] and not lifted.contains(centre - up)[0]
    box = (np.asarray(mission["map"]["min"], float), np.asarray(mission["map"]["max"], float))
    moved = wps.copy()
    moved[change["move_waypoint"]["index"]] = change["move_waypoint"]["position"]
    radius = float(mission["vehicle_radius"]) + allowance
    with pytest.raises(CorridorError):  # the example's own box makes the route unflyable
        build_corridors(moved, [*obstacles, *polys(original["add"])], box, radius)
    corridors = build_corridors(moved, [*obstacles, *polys(popup["add"])], box, radius)
    assert len(corridors) == len(wps) - 1
    # ...and the shifted box still invalidates the curve planned before it popped up
    problem = Problem.from_waypoints(wps, raw["durations"], Bounds.symmetric(7, 6.5, 6, 15),
                                     tuple(build_corridors(wps, obstacles, box, radius)))
    first = plan(problem)
    assert first.ok and first.trajectory is not None
    curve = first.trajectory.evaluate(np.linspace(0, first.trajectory.t_end, 4000))
    (pop,) = polys(popup["add"])
    inflated = Polytope(pop.A, pop.b + radius * np.linalg.norm(pop.A, axis=1))
    assert inflated.contains(curve).any()
