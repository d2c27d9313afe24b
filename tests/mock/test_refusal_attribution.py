"""Issue 26.6: a refusal says who refused. The companion's own check ("vehicle is on the
ground: send 'takeoff' first", after a pilot's mode change on the ground) is `by: companion`
and `python -m companion send` exits 4 on it; the autopilot's refusal of an arm is `by:
autopilot` and exits 5."""

from __future__ import annotations

import asyncio
import socket
import time
from pathlib import Path

from companionkit import Events, service_for, serving, until

from companion.cli_client import EXIT_DENIED, EXIT_REFUSED
from companion.cli_send import outcome
from companion.wire.messages import Command, read
from sitl_mock import ControlClient, MockAutopilot, MockConfig


def _free_tcp() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def test_refusals_say_who_refused_and_send_exits_by_it(tmp_path: Path) -> None:
    ctl = _free_tcp()
    mock = MockAutopilot(MockConfig(autopilot="ardupilot", endpoints=["udpin:127.0.0.1:0"], control=f"127.0.0.1:{ctl}",
                                    log_path=str(tmp_path / "f.jsonl"))).start()

    async def go() -> None:
        svc = service_for(mock)
        events = Events(svc)
        async with serving(svc):
            await until(lambda: svc.link.state.position_problem() is None, 10, "position")
            await svc.commands.arm()  # armed in GUIDED, on the ground
            assert svc.link.state.armed
            with ControlClient("127.0.0.1", ctl) as c:  # a pilot's mode change
                assert c.set_mode("LOITER")["mode"] == "LOITER"
            await until(lambda: svc.flight.state.value == "PILOT", 5, "the pilot's mode seen")
            spec = read("mission", b'{"id": "m", "waypoints": [[2, 0, -1.0]], "autostart": false}', svc.cfg)
            await svc.navigator.on_mission(spec, time.monotonic())  # type: ignore[arg-type]
            assert svc.navigator.pending is not None
            mark = len(events.all)
            await svc.commands.on_command(Command("start"), time.monotonic())
            await until(lambda: any(e["type"] == "refused" for e in events.all[mark:]), 10, "the refusal")
            seen = events.all[mark:]
            refused = next(e for e in seen if e["type"] == "refused")
            assert refused["by"] == "companion", refused
            assert refused["reason"] == "vehicle is on the ground: send 'takeoff' first", refused
            assert [e["type"] for e in seen][:2] == ["accepted", "refused"]
            assert outcome("command", seen) == EXIT_REFUSED
            assert not svc.link.state.in_follow_mode()  # the companion did not take control

            # the autopilot's own refusal: by autopilot, exit 5
            await svc.commands.on_command(Command("disarm"), time.monotonic())
            await until(lambda: not svc.link.state.armed, 15, "disarmed")
            with ControlClient("127.0.0.1", ctl) as c:
                c.reject_arming(True)
            mark = len(events.all)
            await svc.commands.on_command(Command("arm"), time.monotonic())
            await until(lambda: any(e["type"] == "refused" for e in events.all[mark:]), 15, "the arm refusal")
            denied = next(e for e in events.all[mark:] if e["type"] == "refused")
            assert denied["by"] == "autopilot" and denied["reason"].startswith("failed: "), denied
            assert outcome("command", events.all[mark:]) == EXIT_DENIED

    try:
        asyncio.run(go())
    finally:
        mock.stop()


def test_send_exit_code_follows_by() -> None:
    """`by` decides; an event of a companion before `by` existed falls back on "failed:"."""
    ev = {"type": "refused", "key": "command", "reason": "failed: x"}
    assert outcome("command", [{**ev, "by": "companion"}]) == EXIT_REFUSED
    assert outcome("command", [{**ev, "by": "autopilot", "reason": "denied"}]) == EXIT_DENIED
    assert outcome("command", [ev]) == EXIT_DENIED
    assert outcome("command", [{**ev, "reason": "no mission"}]) == EXIT_REFUSED
