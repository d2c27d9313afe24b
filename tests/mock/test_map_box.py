"""The map box (the geofence, shifted by home) and home's validity, against the PX4 mock whose
ground reads z +1.6 in its local frame (issue 20.5): a mission refused because a position is
outside the box says so, with the box and the position, never "an obstacle"; before PX4
reports a valid home (HOME_POSITION at the local origin) a mission on the ground is refused
saying the autopilot is not ready, and planned from where the vehicle is once it is."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
from companionkit import Events, service_for, serving, until

from companion.service import Service
from companion.wire.messages import read
from sitl_mock import MockAutopilot, MockConfig

MISSION = {"id": "square", "frame": "ned", "origin": "local",
           "waypoints": [[2.0, 0.0, -0.5], [2.0, 2.0, -0.5]]}


def _mock(tmp_path: Path) -> MockAutopilot:
    return MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"], ground_z=1.6,
                                    log_path=str(tmp_path / "f.jsonl"), log_rate_hz=10)).start()


async def _send(svc: Service, events: Events, body: dict[str, Any]) -> dict[str, Any]:
    n = len(events.all)
    payload = json.dumps(body).encode()
    st = svc.link.state
    svc.inbound.dispatch("mission", payload, time.monotonic(),
                          read("mission", payload, svc.cfg, st.home, home_pending=st.home_pending))
    await until(lambda: any(e.get("key") == "mission" for e in events.all[n:]), 30, "the mission's answer")
    return next(e for e in events.all[n:] if e.get("key") == "mission")


def test_a_position_outside_the_map_box_is_named_as_such(tmp_path: Path) -> None:
    mock = _mock(tmp_path)

    async def go() -> dict[str, Any]:
        svc = service_for(mock, geofence={"origin": "local"})  # the box in the local frame: floor z 0.5
        events = Events(svc)
        async with serving(svc):
            await until(lambda: svc.link.state.has_position, 10, "a position")
            return await _send(svc, events, MISSION)

    try:
        reply = asyncio.run(go())
    finally:
        mock.stop()
    assert reply["type"] == "rejected", reply
    reason = reply["reason"]
    assert "obstacle" not in reason, reason
    assert "the current position [0, 0, 1.6]" in reason and "below the floor of the map box" in reason, reason
    assert "[-100, -100, -50]..[100, 100, 0.5]" in reason, reason


def test_a_mission_before_home_is_valid_waits_for_the_autopilot(tmp_path: Path) -> None:
    mock = _mock(tmp_path)
    mock.home_ned = np.zeros(3)  # PX4 before its estimator is ready: HOME_POSITION at the origin

    async def go() -> tuple[dict[str, Any], dict[str, Any], Any]:
        svc = service_for(mock)  # [geofence] origin = "home" (default)
        events = Events(svc)
        async with serving(svc):
            await until(lambda: svc.link.state.home_pending and svc.link.state.has_position, 10, "home at origin")
            assert svc.status()["geofence"]["relative_to"] == "local" and svc.status()["home"] is None
            early = await _send(svc, events, MISSION)
            mock.home_ned = np.array([0.0, 0.0, 1.6])  # ready: home where the vehicle stands
            await until(lambda: svc.link.state.home is not None, 10, "a valid home")
            fence = svc.status()["geofence"]  # the box follows home, in the local frame
            assert fence["relative_to"] == "home" and fence["max"][2] == 2.1 and fence["min"][2] == -48.4, fence
            late = await _send(svc, events, {**MISSION, "origin": "home",
                                             "waypoints": [[2.0, 0.0, -1.0], [2.0, 2.0, -1.0]]})
            return early, late, svc.link.state.home

    try:
        early, late, home = asyncio.run(go())
    finally:
        mock.stop()
    assert early["type"] == "rejected" and "not ready" in early["reason"], early
    assert "obstacle" not in early["reason"] and "HOME_POSITION" in early["reason"]
    assert np.allclose(home, [0.0, 0.0, 1.6])
    assert late["type"] == "accepted" and late.get("pending"), late  # planned from where it stands
