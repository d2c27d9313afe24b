"""The companion asks for the telemetry it uses, checks it arrives, and says plainly what is
missing and which autopilot parameter to set; arm/start are refused with that reason."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

from companionkit import Events, service_for, serving, until

from companion.wire.messages import Command
from sitl_mock import MockAutopilot, MockConfig


async def _run(mock: MockAutopilot, check: Any) -> None:
    svc = service_for(mock)
    events = Events(svc)
    async with serving(svc):
        await until(lambda: events.of("telemetry"), 10, "the telemetry check")
        await check(svc, events)


def test_streams_requested_on_a_fresh_ardupilot_link(tmp_path: Path) -> None:
    mock = MockAutopilot(MockConfig(autopilot="ardupilot", endpoints=["udpin:127.0.0.1:0"],
                                    log_path=str(tmp_path / "f.jsonl"),
                                    ekf_origin_delay_s=0.0)).start()  # FAST: not about the EKF origin

    async def check(svc: Any, events: Events) -> None:
        ev = events.of("telemetry")[-1]
        assert ev["missing"] == [], ev["message"]
        assert svc.link.state.position_problem() is None
        assert svc.link.state.landed_state == 1  # EXTENDED_SYS_STATE: on the ground

    try:
        asyncio.run(_run(mock, check))
    finally:
        mock.stop()


def test_missing_streams_are_reported_with_the_parameter_to_set(tmp_path: Path) -> None:
    mock = MockAutopilot(MockConfig(autopilot="ardupilot", endpoints=["udpin:127.0.0.1:0"],
                                    log_path=str(tmp_path / "f.jsonl"),
                                    ekf_origin_delay_s=0.0)).start()  # FAST: not about the EKF origin
    # an autopilot that ignores every stream request (say, an old firmware on a busy link)
    mock._set_interval = lambda msg_id, us: (4, "denied")  # type: ignore[method-assign]  # MAV_RESULT_DENIED
    mock._on_request_data_stream = lambda msg: None  # type: ignore[method-assign]

    async def check(svc: Any, events: Events) -> None:
        ev = events.of("telemetry")[-1]
        assert set(ev["missing"]) == {"LOCAL_POSITION_NED", "ATTITUDE", "EXTENDED_SYS_STATE"}
        assert "MAV1_POSITION" in ev["message"] and "MAV1_EXTRA1" in ev["message"]
        await svc.commands.on_command(Command("arm"), 0.0)
        refused = events.of("refused")[-1]
        assert refused["command"] == "arm" and "MAV1_POSITION" in refused["reason"], refused
        assert not mock.snapshot()["armed"]

    try:
        asyncio.run(_run(mock, check))
    finally:
        mock.stop()


def test_waiting_for_a_heartbeat_is_said() -> None:
    from companionkit import free_tcp

    from companion.config import config_from_dict
    from companion.service import Service

    async def go() -> None:
        svc = Service(config_from_dict({
            "mavlink": {"url": "udpin:127.0.0.1:0"},  # nobody will send
            "zenoh": {"listen": [f"tcp/127.0.0.1:{free_tcp()}"], "multicast_scouting": False},
            "planner": {"executor": "thread"}}))
        events = Events(svc)
        task = asyncio.create_task(svc.run())
        try:
            await until(lambda: events.of("link"), 60, "the waiting line")
            assert "waiting for autopilot heartbeat on udpin:127.0.0.1:0" in events.of("link")[0]["message"]
            assert not svc.flight.seen_link
        finally:
            svc.requested.set()
            assert await asyncio.wait_for(task, 30)  # nothing to hand over

    asyncio.run(go())
