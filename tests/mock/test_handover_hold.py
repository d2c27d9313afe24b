"""The hand-over is confirmed by watching the vehicle, and never goes to a pilot mode when no
pilot is known (issue 20.1; docs/handover.md). In process: the service against the in-process
ArduPilot mock, stopped as SIGTERM stops it (`requested`), after a takeoff."""

from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from companionkit import Events, service_for, up

from sitl_mock import MockAutopilot, MockConfig


def _mock(tmp_path: Path) -> MockAutopilot:
    return MockAutopilot(MockConfig(autopilot="ardupilot", endpoints=["udpin:127.0.0.1:0"],
                                    log_path=str(tmp_path / "flight.jsonl"), log_rate_hz=50)).start()


def _push_down_in(mock: MockAutopilot, mode: str, stop: threading.Event) -> None:
    """Once the vehicle is in `mode`, a strong downward gust: the vehicle sinks ~3 m (the mock's
    hold is a P controller) as ArduCopter's LOITER sinks with no pilot input."""
    while not stop.is_set():
        if mock.snapshot()["mode"] == mode:
            mock.wind = np.array([0.0, 0.0, 40.0])
            return
        time.sleep(0.01)


async def _fly_then_stop(mock: MockAutopilot, **safety: Any) -> tuple[bool, Events, dict[str, Any]]:
    svc = service_for(mock, safety={"takeoff_altitude": 1.5, **safety})
    events = Events(svc)
    task = asyncio.create_task(svc.run())
    await up(svc, task)
    await svc.commands.takeoff(1.5)
    assert svc.flight.state.value == "READY" and svc.flight.airborne
    await asyncio.sleep(0.3)
    svc.requested.set()
    handed_over = await asyncio.wait_for(task, 30)
    return handed_over, events, mock.snapshot()


def test_a_hand_over_to_a_mode_where_the_vehicle_sinks_is_reported_as_failed(tmp_path: Path) -> None:
    mock = _mock(tmp_path)
    stop = threading.Event()
    gust = threading.Thread(target=_push_down_in, args=(mock, "LOITER", stop), daemon=True)
    gust.start()
    try:
        handed_over, events, _ = asyncio.run(_fly_then_stop(mock, exit_pilot_mode="LOITER", pilot_present=True))
    finally:
        stop.set()
        mock.stop()
    assert handed_over is False  # `python -m companion run` exits 1 on this
    last = events.of("handover")[-1]
    assert last["held"] is False and last["mode"] == "LOITER", last
    assert "descend" in last["message"], last  # said as it is: the vehicle sinks (+z NED)
    assert events.of("stopped")[-1]["handed_over"] is False


def test_a_pilot_mode_is_not_used_without_a_known_pilot(tmp_path: Path) -> None:
    mock = _mock(tmp_path)
    try:
        handed_over, events, snap = asyncio.run(_fly_then_stop(mock, exit_pilot_mode="LOITER"))
        time.sleep(3.5)  # past GUID_TIMEOUT: GUIDED keeps the position target
        later = mock.snapshot()
    finally:
        mock.stop()
    assert handed_over is True
    said = events.of("handover")
    assert said[0].get("pilot_mode_refused") and "no pilot is known present" in said[0]["message"], said
    assert said[-1]["held"] is True and said[-1]["mode"] == "GUIDED", said
    assert snap["mode"] == later["mode"] == "GUIDED" and later["armed"] and not later["landed"]
    assert abs(later["position"][2] - snap["position"][2]) <= 0.2


def test_after_a_long_stall_ardupilot_is_asked_for_brake_not_loiter(tmp_path: Path) -> None:
    """The companion stalled long enough that its setpoints stopped: it releases control and asks
    for an autonomous hold (BRAKE: it holds until the mode changes), never LOITER (a pilot mode
    that descends with no RC input on ArduCopter)."""
    mock = _mock(tmp_path)
    limit = 0.5

    async def go() -> tuple[Events, float, dict[str, Any]]:
        svc = service_for(mock, safety={"takeoff_altitude": 1.5}, setpoints={"loop_stall_limit": limit})
        events = Events(svc)
        task = asyncio.create_task(svc.run())
        try:
            await up(svc, task)
            await svc.commands.takeoff(1.5)
            await asyncio.sleep(0.3)
            z0 = mock.snapshot()["position"][2]
            time.sleep(limit + 0.7)  # the loop blocked: setpoints withheld for longer than 0.5 s
            deadline = time.monotonic() + 10
            while not any(e["type"] == "handover" for e in events.all):
                assert time.monotonic() < deadline, [e["type"] for e in events.all][-10:]
                await asyncio.sleep(0.05)
            await asyncio.sleep(4.0)  # BRAKE holds
            return events, z0, mock.snapshot()
        finally:
            svc.requested.set()
            await asyncio.wait_for(task, 30)

    try:
        events, z0, snap = asyncio.run(go())
    finally:
        mock.stop()
    said = [e for e in events.all if e["type"] == "handover"]
    assert said[0]["mode"] == "BRAKE" and said[0].get("cause") == "companion", said
    assert snap["mode"] == "BRAKE" and snap["armed"] and not snap["landed"]
    assert abs(snap["position"][2] - z0) <= 0.3


def test_a_pilot_is_known_present_only_from_a_live_centred_transmitter_or_the_config() -> None:
    from companion.config import config_from_dict
    from companion.handover import HandOver
    from companion.report import Reporter
    from companion.supervisor import Supervisor
    from companion.wire.mavlink import MavlinkLink

    def plan(safety: dict[str, Any], throttle: int | None, age: float = 0.1) -> str:
        cfg = config_from_dict({"safety": safety})
        link = MavlinkLink(cfg)
        link.state.autopilot = "ardupilot"
        if throttle is not None:
            link.state.rc_throttle, link.state.last_rc = throttle, time.monotonic() - age
        said: list[dict[str, Any]] = []
        flight = Supervisor()
        handover = HandOver(cfg, flight, None, link, None,  # type: ignore[arg-type]
                            Reporter(flight, lambda k, b: said.append(b)), lambda: None)
        return handover.exit_plan(stream_works=True)[0]

    loiter = {"exit_pilot_mode": "LOITER"}
    assert plan(loiter, None) == "GUIDED"  # no RC heard: no pilot
    assert plan(loiter, 1000) == "GUIDED"  # SITL's RC with no transmitter: throttle at minimum
    assert plan(loiter, 1500, age=3.0) == "GUIDED"  # a transmitter last heard 3 s ago
    assert plan(loiter, 1500) == "LOITER"  # live, centred: the pilot mode would hold
    assert plan({**loiter, "pilot_present": True}, None) == "LOITER"
    assert plan({}, 1500) == "GUIDED"  # no pilot mode configured
