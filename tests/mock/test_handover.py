"""The hand-over on an internal failure, in process: the service against the in-process mock.

The setpoint sender (thread or process) fails while the vehicle holds in OFFBOARD/GUIDED in the air: the service
must ask for the autopilot's own hold (and see it confirmed) before it stops, so the
autopilot's offboard-loss failsafe never fires; then `run()` raises what failed.
"""

from __future__ import annotations

import asyncio
import json
import os
import signal
import socket
import time
from pathlib import Path

import pytest

from companion.config import config_from_dict
from companion.service import Service
from sitl_mock import MockAutopilot, MockConfig


def _free_tcp() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Broken:
    """A feed whose trajectory cannot be sampled: the setpoint thread raises on it."""

    @property
    def trajectory(self) -> object:
        raise RuntimeError("injected failure")

    t_base = 0.0


async def _fly_then_fail(autopilot: str, log_path: Path, process: bool) -> tuple[Service, BaseException | None]:
    mock = MockAutopilot(MockConfig(autopilot=autopilot, endpoints=["udpin:127.0.0.1:0"], log_path=str(log_path),
                                    log_rate_hz=50,
                                    ekf_origin_delay_s=0.0)).start()  # FAST: not about the EKF origin
    try:
        port = mock.addresses[0][1]
        cfg = config_from_dict({
            "vehicle": {"id": "handover"},
            "mavlink": {"url": f"udpout:127.0.0.1:{port}"},
            "zenoh": {"listen": [f"tcp/127.0.0.1:{_free_tcp()}"], "multicast_scouting": False},
            "planner": {"executor": "thread"},
            "safety": {"takeoff_altitude": 1.0},
            "setpoints": {"process": process},
        })
        svc = Service(cfg)
        task = asyncio.create_task(svc.run())
        deadline = time.monotonic() + 60
        while not (svc.flight.seen_link and svc.link.state.has_position and svc.sender.native_id is not None
                   and svc._sender_failure is not None):
            assert time.monotonic() < deadline and not task.done(), "service did not come up"
            await asyncio.sleep(0.05)
        await svc.commands.takeoff(1.0)  # arms first (as auto_arm would)
        assert svc.flight.state.value == "READY" and svc.flight.airborne
        await asyncio.sleep(0.5)
        if process:  # the setpoint process dies (a crash, the OOM killer)
            assert svc.sender.native_id is not None
            os.kill(svc.sender.native_id, signal.SIGKILL)
        else:  # the setpoint thread raises
            svc.sender.feed = Broken()  # type: ignore[assignment]
        failure: BaseException | None = None
        try:
            await asyncio.wait_for(task, 30)
        except Exception as exc:
            failure = exc
        return svc, failure
    finally:
        time.sleep(1.5)  # longer than COM_OF_LOSS_T: a failsafe would show in the log
        mock.stop()


@pytest.mark.parametrize(("autopilot", "process"), [("px4", False), ("ardupilot", False), ("px4", True),
                                                     ("ardupilot", True)])
def test_setpoint_sender_failure_hands_over_to_the_autopilot(autopilot: str, process: bool, tmp_path: Path) -> None:
    log_path = tmp_path / "flight.jsonl"
    svc, failure = asyncio.run(_fly_then_fail(autopilot, log_path, process))
    assert failure is not None and f"setpoint {'process' if process else 'thread'} failed" in str(failure)
    records = [json.loads(line) for line in log_path.read_text().splitlines() if line.strip()]
    # an autonomous hold, never a pilot mode (docs/handover.md): PX4 AUTO.LOITER; ArduPilot BRAKE,
    # as no setpoint (nor GUIDED's position target) can be sent without the setpoint thread
    hold_mode = "LOITER" if autopilot == "px4" else "BRAKE"
    modes = [r for r in records if r["type"] == "mode"]
    events = [(r["t"], r.get("event"), r.get("reason") or r.get("cause")) for r in records if r["type"] == "event"]
    assert modes[-1]["to"] == hold_mode and modes[-1]["reason"] == "command", (
        [(m["t"], m["to"], m.get("reason")) for m in modes[-3:]], events[-5:])
    assert not [r for r in records if r["type"] == "event" and r.get("event") == "failsafe"]
    last = [r for r in records if r["type"] == "state"][-1]
    assert last["armed"] and not last["landed"] and last["mode"] == hold_mode
    assert svc.flight.state.value == "PILOT"
