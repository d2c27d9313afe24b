"""A PX4 climb planned too late on a busy computer (field: CI's loaded runner refused a takeoff
because "the split time had passed when the plan was ready (planning took 0.98 s, twice)"). From
a hold the same climb may start later: it is moved to the next split, not planned again."""

from __future__ import annotations

import asyncio
from pathlib import Path
from typing import Any

import numpy as np
from companionkit import Events, service_for, serving, until

import planner_core
from sitl_mock import MockAutopilot, MockConfig


def test_a_climb_planned_too_late_is_moved_to_a_later_split_not_refused(tmp_path: Path) -> None:
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"], px4_ready_s=0.0,
                                    log_path=str(tmp_path / "f.jsonl"))).start()
    planned: list[Any] = []

    async def go() -> None:
        svc = service_for(mock, planner={"split_ahead": 0.3})
        events = Events(svc)
        real = svc.runtime.plan
        delays = iter([1.5, 3.5])  # each climb plan slower than the last: a load that grows

        async def slow(fn: Any, *args: Any, **kw: Any) -> Any:
            out = await real(fn, *args, **kw)
            if fn is planner_core.plan:
                planned.append(out.trajectory)
                await asyncio.sleep(next(delays))
            return out

        svc.runtime.plan = slow  # type: ignore[method-assign]
        async with serving(svc):
            await until(lambda: svc.link.state.position_problem() is None, 20, "position")
            await svc.commands.takeoff(1.5)
            refused = [e for e in events.of("refused") if e.get("command") == "takeoff"]
            assert not refused, refused
            assert svc.flight.state.value == "READY" and svc.flight.airborne
            assert len(planned) == 1  # moved, not planned again
            flown = svc.control.active
            assert flown is not None
            climb = planned[0]
            k = climb.n_segments
            shift = flown.times[-1] - climb.times[-1]
            assert shift >= 1.0  # it starts later than planned, by about the planning time
            assert np.array_equal(flown.control_points[-k:], climb.control_points)  # the same curve
            assert np.allclose(flown.times[-k - 1:], climb.times + shift, atol=1e-9)
            assert abs(mock.snapshot()["position"][2] - (mock.ground_z - 1.5)) < 0.3

    try:
        asyncio.run(go())
    finally:
        mock.stop()
