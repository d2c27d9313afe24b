"""A TCP link to an autopilot that dies and comes back (field finding: ArduCopter SITL over
`tcp:127.0.0.1:5760`, the SITL process died).

pymavlink's own TCP reconnect (mavtcp autoreconnect: 6 tries, 1 s apart, inside recv and write)
ran on the companion's event loop and froze it for seconds at a time, and the setpoint process
went on writing to the descriptor of the dead connection. Here the mock autopilot serves TCP as
ArduPilot SITL serves SERIAL0; it is stopped while the companion holds the vehicle in the air,
then a new one is started on the same port (a restarted SITL: on the ground, disarmed):

- the event loop keeps running throughout (a 10 ms ticker never waits long);
- the outage is handled as any lost link (`link_lost`, cause the link; control released);
- the companion reconnects by itself and streams nothing to the new autopilot until it is
  commanded again (`arm`, `takeoff`: the new one is on the ground); then its setpoints reach
  the new autopilot on the new connection.
"""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import pytest
from companionkit import Events, service_for, serving, until
from mockkit import free_tcp_port

from companion.flight import State
from companion.wire.messages import Command
from sitl_mock import MockAutopilot, MockConfig, read_log

OUTAGE = 4.0  # s without the autopilot: over link_timeout (1.5 s), and over pymavlink's 1 s retry sleeps
LOOP_GAP_MAX = 0.5  # s: generous for a loaded machine; pymavlink's reconnect held the loop ~4-6 s


def _mock(port: int, log: Path) -> MockAutopilot:
    return MockAutopilot(MockConfig(autopilot="ardupilot", endpoints=[f"tcpin:127.0.0.1:{port}"],
                                    log_path=str(log), log_rate_hz=10, spool_up_s=0.5)).start()


async def _ticker(gaps: list[float], stop: asyncio.Event) -> None:
    """The longest wait of a 10 ms sleep on the loop (in gaps[0])."""
    last = time.monotonic()
    while not stop.is_set():
        await asyncio.sleep(0.01)
        now = time.monotonic()
        gaps[0] = max(gaps[0], now - last)
        last = now


@pytest.mark.parametrize("process", [True, False], ids=["process", "thread"])
def test_a_tcp_autopilot_that_dies_and_comes_back(tmp_path: Path, process: bool) -> None:
    port = free_tcp_port()
    first = _mock(port, tmp_path / "first.jsonl")
    second: MockAutopilot | None = None

    async def go() -> float:
        nonlocal second
        svc = service_for(first, mavlink={"url": f"tcp:127.0.0.1:{port}"},
                          setpoints={"process": process})
        events = Events(svc)
        async with serving(svc):
            await until(lambda: svc.link.state.has_position, 20, "a position")
            await svc.commands.takeoff(1.0)
            assert svc.flight.state is State.READY and svc.control.streaming
            sent = svc.link.sent_setpoints
            await asyncio.sleep(0.5)
            assert svc.link.sent_setpoints > sent, "no setpoint streamed before the outage"

            gaps, stop = [0.0], asyncio.Event()
            ticker = asyncio.create_task(_ticker(gaps, stop))
            first.stop()  # the listening socket and the connection closed: the SITL process died
            lost_at = time.monotonic()
            await until(lambda: events.of("link_lost"), 5, "link lost")
            assert events.of("link_lost")[0]["cause"] == "link"
            assert svc.flight.state is State.FAILSAFE and not svc.control.streaming
            await asyncio.sleep(max(0.0, lost_at + OUTAGE - time.monotonic()))

            second = _mock(port, tmp_path / "second.jsonl")  # the SITL restarted, same port
            await until(lambda: events.of("link_restored"), 10, "link restored")
            await asyncio.sleep(1.0)  # a restored link alone must not resume the stream
            stop.set()
            await ticker
            print(f"longest wait of a 10 ms sleep over the outage: {gaps[0] * 1000:.0f} ms")
            assert gaps[0] < LOOP_GAP_MAX, f"the event loop was blocked for {gaps[0]:.2f} s"
            # the loop ran: the outage is the link's, not a stall of the companion
            assert not events.of("stalled"), events.of("stalled")
            assert not [e for e in events.all if e["type"] == "error" and "loop_stall_ms" in e], events.all

            started_at = second.snapshot()["t"]
            for cmd in (Command("arm"), Command("takeoff", 1.0)):
                await svc.commands.on_command(cmd, time.monotonic())
                await until(lambda c=cmd.name: [e for e in events.all if e.get("command") == c
                                                and e["type"] in ("completed", "refused")], 60, f"{cmd.name} done")
            assert [e["command"] for e in events.of("completed")][-2:] == ["arm", "takeoff"], events.of("refused")
            assert svc.flight.state is State.READY and svc.control.streaming
            await asyncio.sleep(1.0)
        return started_at

    try:
        started_at = asyncio.run(go())
    finally:
        first.stop()
        if second is not None:
            second.stop()
    assert second is not None
    setpoints = [r for r in read_log(tmp_path / "second.jsonl") if r["type"] == "setpoint"]
    # nothing of the plan flown before the outage reached the new autopilot: only what arm/takeoff made
    assert setpoints and min(r["t"] for r in setpoints) >= started_at, setpoints[:3]
    applied = [r for r in setpoints if r["valid"] and r["applied"]]
    assert len(applied) > 25, f"only {len(applied)} setpoints applied on the new connection"


class _NotYet:
    """Where `service_for` finds the autopilot's port, before any autopilot listens there."""

    def __init__(self, port: int) -> None:
        self.addresses = [("127.0.0.1", port)]


def test_a_tcp_autopilot_not_listening_yet_is_waited_for(tmp_path: Path) -> None:
    """The service starts with nothing on the port (SITL not started yet), as on UDP, and finds the
    autopilot once it listens; connecting never holds up the loop (pymavlink's mavtcp dialled in
    its constructor, 6 tries 1 s apart, then the service failed to start)."""
    port = free_tcp_port()
    mock: MockAutopilot | None = None

    async def go() -> None:
        nonlocal mock
        svc = service_for(_NotYet(port), mavlink={"url": f"tcp:127.0.0.1:{port}"})  # type: ignore[arg-type]
        events = Events(svc)
        task = asyncio.create_task(svc.run())
        try:
            await until(lambda: task.done() or (svc._sender_failure is not None and svc.sender.native_id is not None),
                        60, "the service running")
            assert not task.done(), task
            gaps, stop = [0.0], asyncio.Event()
            ticker = asyncio.create_task(_ticker(gaps, stop))
            await asyncio.sleep(2.5)  # nothing listens: the dialler tries again and again
            assert not svc.flight.seen_link and not task.done()
            assert [e for e in events.of("link") if "waiting for autopilot heartbeat" in e["message"]]
            mock = _mock(port, tmp_path / "late.jsonl")
            await until(lambda: svc.flight.seen_link, 10, "the autopilot found")
            await until(lambda: svc.link.state.has_position, 10, "a position")
            stop.set()
            await ticker
            assert gaps[0] < LOOP_GAP_MAX, f"the event loop was blocked for {gaps[0]:.2f} s"
        finally:
            svc.requested.set()
            await asyncio.wait_for(task, 30)

    try:
        asyncio.run(go())
    finally:
        if mock is not None:
            mock.stop()
