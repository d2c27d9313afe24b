"""Issue 20: on PX4 SIH (9ececfdd, stock config) missions flown with `[planner] tracking_allowance`
0.40 m braked themselves 2.4-4.6 s after their start ("tracking error 0.41-0.43 m"): PX4's
estimate strays ~0.4 m from the setpoint even while holding. The PX4 mock's estimate does the
same in OFFBOARD (sitl_mock.px4 OFFBOARD_WANDER_*) on PX4 SIH's response (~0.3 s lag), so the
old ArduPilot-sized allowance fails against it as it failed on PX4; the default ("autopilot":
PX4's 1.0 m, with which the same missions flew on PX4 SIH) flies the mission to its end."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

from companionkit import Events, service_for, serving, until

from companion.service import Service
from companion.wire.messages import MissionSpec, read
from sitl_mock import MockAutopilot, MockConfig
from sitl_mock.vehicle import RESPONSES

# an L out and back, 2 m above home: ~20 m at up to the default bounds
MISSION = b'{"id": "ell", "origin": "home", "waypoints": [[6, 0, -2], [6, 6, -2], [0, 6, -2], [0, 0, -2]]}'


def px4_sih(tmp_path: Path) -> MockAutopilot:
    """The PX4 mock as PX4 SIH responds (the conftest's default for PX4 is the calibrated one)."""
    return MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"], vehicle=RESPONSES["px4_sih"],
                                    log_path=str(tmp_path / "f.jsonl"))).start()


async def fly_mission(svc: Service, events: Events) -> None:
    """Take off 2 m, send MISSION, wait until it completes or the companion brakes."""
    st = svc.link.state
    await until(lambda: st.position_problem() is None and st.home is not None, 10, "position and home")
    await svc.commands.takeoff(2.0)
    spec = read("mission", MISSION, svc.cfg, st.home, autopilot=st.autopilot)
    assert isinstance(spec, MissionSpec), spec
    await svc.navigator.on_mission(spec, time.monotonic())
    await until(lambda: events.of("mission_complete") or events.of("tracking"), 60, "the mission's end or a brake")


def test_px4_mission_at_the_old_040_allowance_brakes_itself(tmp_path: Path) -> None:
    mock = px4_sih(tmp_path)

    async def go() -> dict[str, Any]:
        svc = service_for(mock, planner={"tracking_allowance": 0.4})  # the old default, set explicitly
        events = Events(svc)
        async with serving(svc):
            await fly_mission(svc, events)
            assert not events.of("mission_complete"), "flew the whole mission at 0.40 m"
            ev = events.of("tracking")[0]
            await until(lambda: svc.flight.state.value == "HOLDING", 15, "holding")
            assert svc.navigator.interrupted is not None  # braked: the rest waits for `resume`
            return ev

    try:
        ev = asyncio.run(go())
    finally:
        mock.stop()
    # measured on PX4 SIH: "tracking error 0.41-0.43 m" over 0.40 m
    assert ev["limit"] == 0.4 and ev["error"] > 0.4 and ev["samples"] >= 3, ev


def test_px4_mission_with_the_default_config_flies_to_completion(tmp_path: Path) -> None:
    mock = px4_sih(tmp_path)

    async def go() -> tuple[dict[str, Any], list[dict[str, Any]], float]:
        svc = service_for(mock)  # [planner] tracking_allowance unset: the autopilot's
        events = Events(svc)
        async with serving(svc):
            await fly_mission(svc, events)
            return svc.status(), events.all, svc.tracking.tracking_error_max

    try:
        status, seen, worst = asyncio.run(go())
    finally:
        mock.stop()
    kinds = [e["type"] for e in seen]
    if "mission_complete" not in kinds or "tracking" in kinds:
        raise AssertionError("\n".join(f"{e['type']}: {e['message']}" for e in seen))
    assert status["tracking_allowance"] == 1.0 and "PX4" in status["tracking_allowance_from"]
    said = [e for e in seen if e["type"] == "limits" and "tracking_allowance" in e]
    assert said and said[0]["tracking_allowance"] == 1.0 and "PX4" in said[0]["tracking_allowance_from"]
    # the estimate strays beyond the old 0.40 m on the way, within PX4's allowance
    assert 0.4 < worst < 1.0, worst
