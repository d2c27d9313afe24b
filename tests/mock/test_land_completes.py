"""`land` completes (event `completed`) when the vehicle is on the ground, not when the landing
starts (issue 20.7). In process, against the in-process mock of each flavour."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path
from typing import Any

import pytest
from companionkit import Events, service_for, serving, until

from companion.wire.messages import Command
from sitl_mock import MockAutopilot, MockConfig


async def _land(mock: MockAutopilot) -> tuple[list[dict[str, Any]], dict[str, Any], dict[str, Any]]:
    svc = service_for(mock, safety={"takeoff_altitude": 1.5})
    events = Events(svc)
    async with serving(svc):
        await svc.commands.takeoff(1.5)
        assert svc.flight.airborne and not mock.snapshot()["landed"]
        await svc.commands.on_command(Command("land"), time.monotonic())
        accepted = mock.snapshot()  # the landing has started, the vehicle is still in the air
        await until(lambda: bool(events.of("completed")) or bool(events.of("refused")), 60, "land to complete")
        at_completion = mock.snapshot()
    return events.all, accepted, at_completion


@pytest.mark.parametrize("autopilot", ["px4", "ardupilot"])
def test_land_completes_on_the_ground(autopilot: str, tmp_path: Path) -> None:
    mock = MockAutopilot(MockConfig(autopilot=autopilot, endpoints=["udpin:127.0.0.1:0"],
                                    log_path=str(tmp_path / "flight.jsonl"), log_rate_hz=20)).start()
    try:
        events, accepted, done = asyncio.run(_land(mock))
    finally:
        mock.stop()
    assert not accepted["landed"]
    mine = [e for e in events if e.get("command") == "land" and e["type"] in ("completed", "refused")]
    assert mine and mine[0]["type"] == "completed", mine
    assert done["landed"], done  # on the ground when `completed` was said
    states = [e for e in events if e["type"] == "state"]
    landing = next(i for i, e in enumerate(events) if e["type"] == "state" and e.get("to") == "LANDING")
    assert events.index(mine[0]) > landing and states
