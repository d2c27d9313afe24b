"""The default planner layout flies: missions planned in the planner process (numpy path, no
numba), and a pop-up obstacle on the curve ahead is still avoided by a verified replan."""

from __future__ import annotations

import asyncio
import importlib.util
import json
import sys
import time
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path
from typing import Any

from companionkit import Events, service_for, serving, until

from companion.wire.messages import read
from sitl_mock import MockAutopilot, MockConfig

ROOT = Path(__file__).resolve().parents[2]


def _service_bench() -> Any:
    # the benchmark's pop-up placement: beside the curve, clear of the legs, so a replan exists
    spec = importlib.util.spec_from_file_location("service_bench", ROOT / "benchmarks" / "service.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["service_bench"] = module
    spec.loader.exec_module(module)
    return module


def test_default_layout_plans_in_its_process_and_replans_a_popup(tmp_path: Path) -> None:
    bench = _service_bench()
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"],
                                    log_path=str(tmp_path / "f.jsonl"))).start()

    async def go() -> None:
        # the shipped default layout; a geofence that holds the take-off point wherever the mock
        # puts the ground relative to the local origin
        # (the benchmark's pop-up is placed for an inflation of 0.3 m: vehicle radius + tracking allowance;
        # the PX4 mock's estimate strays 0.42 m from the setpoint, as PX4 SIH's does: brake at PX4's 1.0 m)
        svc = service_for(mock, planner={"executor": "process", "vehicle_radius": 0.1, "tracking_allowance": 0.2},
                          geofence={"min": [-60.0, -60.0, -20.0], "max": [60.0, 60.0, 3.0]},
                          safety={"tracking_brake": 1.0})
        events = Events(svc)
        assert isinstance(svc.runtime.pool, ProcessPoolExecutor)
        assert isinstance(svc.runtime.urgent_pool, ThreadPoolExecutor)
        async with serving(svc):
            await until(lambda: svc.link.state.position_problem() is None, 10, "position")
            await svc.commands.takeoff(1.0)
            mission = read("mission", json.dumps(bench.flight_mission(laps=1)).encode(), svc.cfg)
            await svc.navigator.on_mission(mission, time.monotonic())  # type: ignore[arg-type]
            try:
                await until(lambda: svc.flight.state.value == "STREAMING", 30, "streaming")
            except AssertionError:
                raise AssertionError([(e["type"], e.get("message")) for e in events.all][-8:]) from None
            msg = None
            for i in range(40):  # the climb from the take-off point has no curve beside it
                await asyncio.sleep(0.25)
                traj, to_go = svc.control.active, svc.status().get("time_to_go")
                if traj is not None and to_go is not None:
                    msg = bench.place_popup(traj, traj.t_end - float(to_go), i)
                if msg is not None:
                    break
            assert msg is not None, "no place for a pop-up beside the curve"
            put = time.monotonic()
            await svc.navigator.on_obstacles(read("obstacles", json.dumps(msg).encode(), svc.cfg),  # type: ignore[arg-type]
                                             put)
            await until(lambda: events.of("replanned") or events.of("braking"), 20, "the pop-up's answer")
            assert events.of("replanned"), [(e["type"], e.get("message")) for e in events.all][-6:]
            # the mission itself was planned in the planner process, which never loaded numba
            probe = await svc.runtime.plan(_numba_loaded)
            assert probe is False

    try:
        asyncio.run(go())
    finally:
        mock.stop()


def _numba_loaded() -> bool:
    return "numba" in sys.modules
