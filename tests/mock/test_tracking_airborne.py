"""Tracking errors are judged only in the air, flying or holding a plan of ours after the
takeoff's climb (docs/service.md): real PX4 SIH (1.15) raised `tracking` events on the ground
while arming (0.63 m: its estimate before ready) and during the takeoff climb (0.59 m)."""

from __future__ import annotations

import asyncio
from pathlib import Path

from companionkit import Events, service_for, serving, until

from sitl_mock import MockAutopilot, MockConfig
from sitl_mock.vehicle import RESPONSES


def test_no_tracking_event_while_arming_or_climbing(tmp_path: Path) -> None:
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"], vehicle=RESPONSES["calibrated"],
                                    px4_ready_s=0.0, log_path=str(tmp_path / "f.jsonl"))).start()

    async def go() -> None:
        svc = service_for(mock, planner={"tracking_allowance": 0.2}, safety={"takeoff_altitude": 2.0})
        events = Events(svc)
        async with serving(svc, before_stop=mock.link_faults.heal):
            await until(lambda: svc.link.state.position_problem() is None, 10, "position")
            mock.link_faults.latency_s = 0.3  # the climb trails the plan (0.6 s both ways), as PX4's does
            worst = 0.0
            task = asyncio.create_task(svc.commands.takeoff(2.0))
            while not task.done():
                if svc.flight.state.value in ("ARMING", "TAKEOFF") and svc.tracking.tracking_error is not None:
                    worst = max(worst, svc.tracking.tracking_error)
                await asyncio.sleep(0.02)
            await task
            assert worst > 0.2, worst  # the climb was over the allowance ...
            assert not events.of("tracking"), events.of("tracking")  # ... and not judged
            assert not any(e["type"] == "braking" for e in events.all)
            assert svc.flight.state.value == "READY" and svc.flight.airborne

    try:
        asyncio.run(go())
    finally:
        mock.stop()
