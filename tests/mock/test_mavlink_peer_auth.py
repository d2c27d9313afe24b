"""Issue 21.1: the MAVLink link is bound to one autopilot. A spoofed heartbeat from another UDP
socket neither stops the flight (disarmed) nor steals the setpoints (armed, OFFBOARD); a wrong
system id from the autopilot's own address is ignored; with a signing key, unsigned autopilot
messages are ignored; what is ignored is counted and said. The autopilot is the real mock;
the spoofer raw pymavlink on its own socket (tests/mock/spoofer.py)."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from typing import Any

from companionkit import Events, service_for, serving, until
from mockkit import free_udp_port
from spoofer import ARMED, CUSTOM, PX4_OFFBOARD, Spoofer

from companion.wire.messages import read
from companion.wire.peer import (
    OTHER_ADDRESS,
    OTHER_ID,
    UNSIGNED,
    PeerGate,
    SignatureCheck,
    signing_now,
)
from sitl_mock import MockAutopilot, MockConfig
from sitl_mock.vehicle import RESPONSES

MISSION = (b'{"id": "square", "waypoints": [[5, 0, -1.5], [5, 5, -1.5], [0, 5, -1.5], [0, 0, -1.5]],'
           b' "durations": [3.0, 3.0, 3.0]}')
KEY = bytes(range(32))


def _mock(tmp_path: Path, port: int, name: str = "f", bind: int | None = None, **kw: Any) -> MockAutopilot:
    at = f"@127.0.0.1:{bind}" if bind is not None else ""
    # the response the other in-process flights use (PX4 SIH's 0.3 s lag has tests of its own)
    kw.setdefault("vehicle", RESPONSES["calibrated"])
    return MockAutopilot(MockConfig(autopilot="px4", endpoints=[f"udpout:127.0.0.1:{port}{at}"],
                                    log_path=str(tmp_path / f"{name}.jsonl"), log_rate_hz=50, **kw)).start()


def _log(tmp_path: Path, name: str = "f") -> list[dict[str, Any]]:
    return [json.loads(x) for x in (tmp_path / f"{name}.jsonl").read_text().splitlines() if x.strip()]


def test_spoofed_heartbeats_neither_stop_nor_steal_the_flight(tmp_path: Path) -> None:
    port = free_udp_port()
    mock = _mock(tmp_path, port)
    disarmer, thief = Spoofer(port), Spoofer(port)

    async def go() -> None:
        svc = service_for(mock, mavlink={"url": f"udpin:127.0.0.1:{port}"})
        events = Events(svc)
        async with serving(svc):
            await until(lambda: svc.link.state.position_problem() is None, 10, "position")
            await svc.commands.takeoff(1.5)
            await svc.navigator.on_mission(read("mission", MISSION, svc.cfg), time.monotonic())  # type: ignore[arg-type]
            await until(lambda: svc.flight.state.value == "STREAMING", 10, "streaming")
            sent = svc.link.sent_setpoints
            # the issue's two spoofs: "disarmed" (the companion stopped streaming) and "armed,
            # OFFBOARD" (it sent its setpoints to the spoofer)
            await asyncio.to_thread(disarmer.heartbeat, False, PX4_OFFBOARD, 10)
            await asyncio.to_thread(thief.heartbeat, True, PX4_OFFBOARD, 20)
            assert svc.flight.state.value == "STREAMING" and svc.link.state.armed
            assert svc.link.sent_setpoints > sent + 30  # still streaming, to the autopilot
            await until(lambda: events.of("mission_complete"), 30, "the mission flown to its end")
            await until(lambda: events.of("mavlink_ignored"), 10, "the ignored messages said")
            ev = events.of("mavlink_ignored")[0]
            assert ev["ignored"].get(OTHER_ADDRESS, 0) >= 1 and "another address" in ev["message"]
            assert len(events.of("mavlink_ignored")) <= 2  # rate-limited: 30 spoofs in 2 s, one or two events
            assert svc.status()["mavlink_ignored"][OTHER_ADDRESS] == 30
        assert not events.of("link_lost") and not [e for e in events.all if "disarmed" in e.get("message", "")]

    try:
        asyncio.run(go())
        assert disarmer.received() == {} and thief.received() == {}  # not one message, let alone a setpoint
        log = _log(tmp_path)
        assert not [r for r in log if r["type"] == "event" and r.get("event") == "failsafe"]
        assert any(r["type"] == "setpoint" for r in log)
    finally:
        disarmer.close()
        thief.close()
        mock.stop()


def test_a_wrong_system_id_from_the_autopilots_address_is_ignored(tmp_path: Path) -> None:
    port, mock_port = free_udp_port(), free_udp_port()
    mock = _mock(tmp_path, port, bind=mock_port)

    async def go() -> None:
        svc = service_for(mock, mavlink={"url": f"udpin:127.0.0.1:{port}"})
        events = Events(svc)
        async with serving(svc):
            await until(lambda: svc.link.state.position_problem() is None, 10, "position")
            assert svc.link.gate is not None and svc.link.gate.address == ("127.0.0.1", mock_port)
            # from the autopilot's own address and port, but system 7 (and its component 1)
            spoof = Spoofer(port, sysid=7, bind=("127.0.0.1", mock_port))
            try:
                await asyncio.to_thread(spoof.heartbeat, True, PX4_OFFBOARD, 5)
            finally:
                spoof.close()
            await until(lambda: svc.link.gate is not None and svc.link.gate.ignored.get(OTHER_ID, 0) >= 5, 5,
                        "the wrong id counted")
            assert not svc.link.state.armed and svc.link.state.mode != "OFFBOARD"
            await until(lambda: events.of("mavlink_ignored"), 10, "the ignored messages said")
            assert "another system or component id" in events.of("mavlink_ignored")[0]["message"]

    try:
        asyncio.run(go())
    finally:
        mock.stop()


def test_with_a_key_unsigned_autopilot_messages_are_ignored(tmp_path: Path) -> None:
    key_file = tmp_path / "mavlink.key"
    key_file.write_text(KEY.hex())
    port = free_udp_port()
    # an autopilot that checks our signatures but signs nothing it sends
    mock = _mock(tmp_path, port, signing_key=KEY, sign_outgoing=False)

    async def go(require: bool) -> None:
        svc = service_for(mock, mavlink={"url": f"udpin:127.0.0.1:{port}", "signing_key_file": str(key_file),
                                         "require_signed_inbound": require})
        events = Events(svc)
        task = asyncio.create_task(svc.run())
        try:
            if require:
                await until(lambda: events.of("mavlink_ignored"), 15, "unsigned messages said")
                assert not svc.flight.seen_link and svc.link.state.last_heartbeat < 0
                assert svc.link.gate is not None and svc.link.gate.ignored.get(UNSIGNED, 0) > 0
                assert "unsigned" in events.of("mavlink_ignored")[0]["message"]
            else:  # configured for an autopilot that signs nothing: heard
                await until(lambda: svc.flight.seen_link and svc.link.state.has_position, 15, "the link")
        finally:
            svc.requested.set()
            svc.abandon.set()
            await asyncio.wait_for(task, 30)

    try:
        asyncio.run(go(True))
        asyncio.run(go(False))
    finally:
        mock.stop()


def test_a_new_address_is_bound_only_after_the_old_one_fell_silent(tmp_path: Path) -> None:
    """mavlink-router restarted: the autopilot's messages come from a new port. While the bound
    address is heard, the new one is ignored; after link_timeout of silence, the same ids
    sending an autopilot heartbeat from the new address are re-bound (and said)."""
    port = free_udp_port()
    first = _mock(tmp_path, port, "first")
    second: MockAutopilot | None = None

    async def go() -> None:
        nonlocal second
        svc = service_for(first, mavlink={"url": f"udpin:127.0.0.1:{port}"})
        events = Events(svc)
        async with serving(svc):
            await until(lambda: svc.link.state.position_problem() is None, 10, "position")
            gate = svc.link.gate
            assert gate is not None
            bound = gate.address
            second = _mock(tmp_path, port, "second")
            await asyncio.sleep(2.0)
            assert gate.address == bound and gate.ignored.get(OTHER_ADDRESS, 0) > 20
            first.stop()
            await until(lambda: events.of("mavlink_peer"), 10, "re-bound")
            assert gate.address != bound and "silent" in events.of("mavlink_peer")[0]["message"]
            # the companion now talks to the new address: it answers a command
            await svc.link.request_home()

    try:
        asyncio.run(go())
    finally:
        first.stop()
        if second is not None:
            second.stop()


# -- the gate and the signature check on their own ------------------------------------------------


class _Msg:
    def __init__(self, kind: str = "HEARTBEAT", sysid: int = 1, compid: int = 1, signed: bool = False) -> None:
        self.kind, self.sysid, self.compid, self.signed = kind, sysid, compid, signed
        self.type, self.autopilot = 2, 12  # quadrotor, PX4

    def get_type(self) -> str:
        return self.kind

    def get_srcSystem(self) -> int:
        return self.sysid

    def get_srcComponent(self) -> int:
        return self.compid

    def get_signed(self) -> bool:
        return self.signed


def test_gate_binds_the_first_autopilot_heartbeat_and_rebinds_only_after_silence() -> None:
    gate = PeerGate(1, 1, udp=True, require_signed=False, link_timeout=1.5)
    a, b = ("127.0.0.1", 1000), ("127.0.0.1", 2000)
    assert gate.admit(_Msg("ATTITUDE"), a, 0.0) is not None  # telemetry before a heartbeat binds nothing
    gcs = _Msg()
    gcs.type = 6  # MAV_TYPE_GCS
    assert gate.admit(gcs, a, 0.0) is not None and not gate.bound
    assert gate.admit(_Msg(), a, 0.1) is None and gate.address == a
    assert not gate.address_ok(b, 1.0)  # the bound autopilot was heard 0.9 s ago
    assert gate.address_ok(b, 1.7) and gate.admit(_Msg("ATTITUDE"), b, 1.7) is not None  # only a heartbeat re-binds
    assert gate.admit(_Msg(sysid=2), b, 1.7) is not None  # and only with the bound ids
    assert gate.admit(_Msg(), b, 1.7) is None and gate.address == b and gate.rebinds == [(a, b)]
    signed = PeerGate(1, 1, udp=False, require_signed=True, link_timeout=1.5)
    assert signed.admit(_Msg(), None, 0.0) == UNSIGNED and signed.admit(_Msg(signed=True), None, 0.0) is None


def test_signature_check_follows_the_spec_and_cannot_be_poisoned() -> None:
    from pymavlink.dialects.v20 import common as mav

    class Sink:
        data = b""

        def write(self, b: bytes) -> None:
            Sink.data = bytes(b)

    def packet(key: bytes, stamp: int, link: int = 0) -> bytearray:
        enc = mav.MAVLink(Sink(), srcSystem=1, srcComponent=1)
        enc.signing.secret_key, enc.signing.sign_outgoing, enc.signing.link_id = key, True, link
        enc.signing.timestamp = stamp - 1  # pymavlink adds one per message
        enc.heartbeat_send(2, 12, CUSTOM | ARMED, 0, 4)
        return bytearray(Sink.data)

    rx = mav.MAVLink(None)
    rx.signing.secret_key = KEY
    rx.signing.timestamp = signing_now()
    check = SignatureCheck(rx)
    now = signing_now()
    assert check(packet(KEY, now), 1, 1)
    assert not check(packet(KEY, now), 1, 1)  # a replay: the timestamp must increase
    assert check(packet(KEY, now + 1), 1, 1)
    assert check(packet(KEY, now - 10, link=1), 1, 1)  # another link id: its own stream
    assert not check(packet(KEY, now - 7_000_000, link=2), 1, 1)  # a new stream over a minute old
    # a forged packet with a far-future timestamp does not lock the real stream out
    assert not check(packet(bytes(32), now + 10**9), 1, 1)
    assert check(packet(KEY, now + 2), 1, 1)


def test_udpout_hears_only_its_configured_destination() -> None:
    gate = PeerGate(1, 1, udp=True, require_signed=False, link_timeout=1.5, address=("127.0.0.1", 14550), pinned=True)
    assert not gate.address_ok(("127.0.0.1", 9999), 0.0)
    assert gate.admit(_Msg(), ("127.0.0.1", 9999), 100.0) == OTHER_ADDRESS  # never re-bound, even after silence
    assert gate.admit(_Msg(), ("127.0.0.1", 14550), 0.0) is None and gate.address == ("127.0.0.1", 14550)


def test_the_binding_survives_a_reboot_of_the_autopilot(tmp_path: Path) -> None:
    """Same ids, same address, signed before and after: the link comes back to the same
    autopilot without a re-bind (and its signed stream is still accepted)."""
    from sitl_mock.faults import FaultSpec

    key_file = tmp_path / "mavlink.key"
    key_file.write_text(KEY.hex())
    port = free_udp_port()
    mock = _mock(tmp_path, port, signing_key=KEY, faults=FaultSpec(reboots=[6.0]))

    async def go() -> None:
        svc = service_for(mock, mavlink={"url": f"udpin:127.0.0.1:{port}", "signing_key_file": str(key_file)})
        events = Events(svc)
        async with serving(svc):
            await until(lambda: svc.link.state.position_problem() is None, 15, "position")
            gate = svc.link.gate
            assert gate is not None
            bound = gate.address
            await until(lambda: events.of("link_lost"), 20, "the reboot's silence")
            await until(lambda: events.of("link_restored"), 20, "the autopilot back")
            await until(lambda: svc.link.state.position_problem() is None, 15, "position again")
            assert gate.address == bound and gate.rebinds == [] and not events.of("mavlink_peer")
            assert gate.ignored.get(UNSIGNED, 0) == 0 and gate.ignored.get(OTHER_ADDRESS, 0) == 0

    try:
        asyncio.run(go())
        assert any(r["type"] == "event" and r.get("event") == "reboot" for r in _log(tmp_path))
    finally:
        mock.stop()
