"""With `[safety] tracking_brake` set apart from `[planner] tracking_allowance`, the messages
name the parameter and value each figure comes from (field: with tracking_brake = 0.5 and
tracking_allowance 0.2, the braking and `tracking_margin` messages said "tracking allowance
0.50 m")."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import time
from pathlib import Path

from companionkit import Events, service_for, serving, until

from companion.wire.messages import read
from sitl_mock import MockAutopilot, MockConfig
from sitl_mock.vehicle import RESPONSES


def test_brake_and_margin_messages_name_tracking_brake_and_allowance(tmp_path: Path) -> None:
    # a vehicle 0.5 s late and no lead: it strays ~speed x 0.56 s from the plan
    slow = dataclasses.replace(RESPONSES["calibrated"], delay=0.5)
    mock = MockAutopilot(MockConfig(autopilot="ardupilot", endpoints=["udpin:127.0.0.1:0"], vehicle=slow,
                                    log_path=str(tmp_path / "f.jsonl"))).start()

    async def go() -> None:
        svc = service_for(mock, setpoints={"lead": 0.0}, planner={"tracking_allowance": 0.2},
                          safety={"tracking_brake": 0.6})
        events = Events(svc)
        async with serving(svc):
            await until(lambda: svc.link.state.position_problem() is None, 10, "position")
            await svc.commands.takeoff(1.5)
            z = float(svc.link.state.position[2])
            mission = json.dumps({"id": "sq", "waypoints": [[8, 0, z], [8, 8, z], [0, 8, z]]}).encode()
            await svc.navigator.on_mission(read("mission", mission, svc.cfg), time.monotonic())  # type: ignore[arg-type]
            await until(lambda: events.of("tracking_margin") and events.of("tracking")
                        and svc.flight.state.value == "HOLDING", 40, "the margin event and the brake")
            said = [e["message"] for e in events.all]
            assert not [m for m in said if "allowance 0.60" in m], said
            margin = events.of("tracking_margin")[0]
            assert "[safety] tracking_brake 0.60 m" in margin["message"], margin["message"]
            assert "[planner] tracking_allowance 0.20 m" in margin["message"], margin["message"]
            assert margin["limit_name"] == "[safety] tracking_brake" and margin["tracking_allowance"] == 0.2
            brake = events.of("tracking")[0]
            assert "[safety] tracking_brake 0.60 m" in brake["message"], brake["message"]
            braking = [e for e in events.all if e["type"] in ("braking", "state") and "tracking error" in e["message"]]
            assert braking and all("[safety] tracking_brake 0.60 m" in e["message"] for e in braking), braking

    try:
        asyncio.run(go())
    finally:
        mock.stop()
