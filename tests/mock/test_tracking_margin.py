"""Issue 26.4: the tracking measured in flight is compared with `[planner] tracking_allowance`
(the margin obstacles are inflated by): when the RMS or the largest error nears it, the
companion says so (`tracking_margin`), before the brake that fires at the allowance itself."""

from __future__ import annotations

import asyncio
import dataclasses
import json
import time
from pathlib import Path

from companionkit import Events, service_for, serving, until

from companion.tracking import TRACKING_MAX_SHARE, TRACKING_RMS_SHARE
from companion.wire.messages import read
from sitl_mock import MockAutopilot, MockConfig
from sitl_mock.vehicle import RESPONSES


def test_tracking_near_the_allowance_is_said(tmp_path: Path) -> None:
    # a vehicle 0.3 s late and no lead: it strays ~speed x 0.36 s from the plan
    slow = dataclasses.replace(RESPONSES["calibrated"], delay=0.3)
    mock = MockAutopilot(MockConfig(autopilot="ardupilot", endpoints=["udpin:127.0.0.1:0"], vehicle=slow,
                                    log_path=str(tmp_path / "f.jsonl"))).start()

    async def go() -> None:
        svc = service_for(mock, setpoints={"lead": 0.0}, planner={"tracking_allowance": 0.6})
        events = Events(svc)
        async with serving(svc):
            await until(lambda: svc.link.state.position_problem() is None, 10, "position")
            await svc.commands.takeoff(1.5)
            z = float(svc.link.state.position[2])
            mission = json.dumps({"id": "sq", "waypoints": [[8, 0, z], [8, 8, z], [0, 8, z]]}).encode()
            await svc.navigator.on_mission(read("mission", mission, svc.cfg), time.monotonic())  # type: ignore[arg-type]
            await until(lambda: (svc.flight.state.value != "STREAMING" and svc.navigator.route is None)
                        or events.of("tracking_margin") or events.of("tracking"), 40, "the margin event")
            margin = events.of("tracking_margin")
            assert margin, [(e["type"], e["message"]) for e in events.all][-6:]
            ev = margin[0]
            assert ev["limit"] == 0.6
            assert ev["rms"] >= TRACKING_RMS_SHARE * 0.6 or ev["max"] >= TRACKING_MAX_SHARE * 0.6
            assert "tracking_allowance" in ev["message"]
            # said before any brake at the allowance, and once
            brakes = [i for i, e in enumerate(events.all) if e["type"] == "tracking"]
            assert not brakes or events.all.index(ev) < brakes[0]
            await asyncio.sleep(1.0)
            assert len(events.of("tracking_margin")) == 1

    try:
        asyncio.run(go())
    finally:
        mock.stop()
