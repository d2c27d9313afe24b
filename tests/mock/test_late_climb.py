"""A takeoff climb whose plan comes back late (a busy computer: the planner process waited for a
core) is planned again further ahead from the hold, not refused (issue 21: on a loaded 2-core
machine the climb's plan took longer than its 0.15 s split and `takeoff` failed, the vehicle
left armed on the ground in OFFBOARD until PX4's failsafe disarmed it)."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import pytest
from companionkit import Events, service_for, serving, until

from sitl_mock import MockAutopilot, MockConfig
from sitl_mock.vehicle import RESPONSES


@pytest.mark.parametrize("late", [1, 2])
def test_a_late_climb_plan_is_planned_again_further_ahead(tmp_path: Path, late: int) -> None:
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"], vehicle=RESPONSES["ideal"],
                                    log_path=str(tmp_path / "f.jsonl"))).start()

    async def go() -> None:
        svc = service_for(mock)
        events = Events(svc)
        runtime = svc.navigator.runtime
        real = runtime.plan
        calls: list[float] = []

        async def slow_plan(fn: Any, *args: Any, **kw: Any) -> Any:
            calls.append(0.0)
            if len(calls) <= late:  # past the split chosen from the measured planning time, by far
                # (the retry splits further ahead by what the first took: the second must be later still)
                await asyncio.sleep((2.0 * svc.navigator.budget.split_ahead_for(2) + 0.3) * (4.0 if len(calls) == 2 else 1.0))
            return await real(fn, *args, **kw)

        async with serving(svc):
            await until(lambda: svc.link.state.position_problem() is None, 20, "a position")
            await svc.commands.arm()
            runtime.plan = slow_plan  # type: ignore[method-assign]
            try:
                if late == 1:
                    await svc.commands.takeoff(1.0)
                    assert svc.flight.airborne and svc.flight.state.value == "READY"
                    assert len(calls) == 2  # planned twice: the second within its (later) split
                else:  # late twice: refused with the real cause, the vehicle still held
                    with pytest.raises(Exception, match=r"planning took .* s, twice"):
                        await svc.commands.takeoff(1.0)
                    assert svc.control.streaming and not events.of("stalled")
            finally:
                runtime.plan = real  # type: ignore[method-assign]

    try:
        asyncio.run(go())
    finally:
        mock.stop()
