"""The PX4 flavour before its estimator settles, and its metadata over MAVLink FTP (pymavlink client)."""

from __future__ import annotations

import json
import lzma
import struct
import time
import zlib
from typing import Any

import pytest
from mockkit import Client
from pymavlink.dialects.v20 import common as mav

from sitl_mock import MockAutopilot
from sitl_mock import events as px4_events
from sitl_mock.__main__ import build_parser

HEADER = struct.Struct("<HBBBBBBI")  # MAVLink FTP payload header (mavlink.io/en/services/ftp.html)
ARM = mav.MAV_CMD_COMPONENT_ARM_DISARM


def event_ids(msgs: list[Any]) -> list[int]:
    return [int(m.id) for m in msgs if m.get_type() == "EVENT"]


def event_args(msgs: list[Any], name: str) -> bytes:
    m = next(m for m in msgs if m.get_type() == "EVENT" and int(m.id) == px4_events.IDS[name])
    return bytes(m.arguments).ljust(40, b"\0")


def test_arming_refused_until_ready_with_px4s_events_then_allowed(make_mock) -> None:  # type: ignore[no-untyped-def]
    # the report every 6 s of simulated time (1.5 s here) instead of 28, for the test's time
    mock, c = make_mock("px4", speed=4.0, px4_ready_s=12.0, px4_report_every_s=6.0)
    # the reasons come in PX4's arming-check report, sent when the checks change ...
    def is_event(name: str) -> Any:
        return lambda m: m.get_type() == "EVENT" and int(m.id) == px4_events.IDS[name]

    first = c.collect(3.0, until=is_event("commander_arming_check_summary"))  # a whole report: from its start
    seen = first[-1:] + c.collect(1.0, until=is_event("commander_health_summary"))
    ids = event_ids(seen)
    assert {25948424, 30612409, 27825120, 18691879} <= set(ids), ids  # reasons, arming and health summaries
    chunk, error, warning, can_arm = struct.unpack_from("<BIII", event_args(seen, "commander_arming_check_summary"))
    local = px4_events.HEALTH_BIT["local_position_estimate"]
    offboard, manual = 1 << px4_events.NAV_STATE["offboard"], 1 << px4_events.NAV_STATE["manual"]
    assert (chunk, error, warning) == (0, local, 0) and not can_arm & offboard and can_arm & manual
    modes, component = struct.unpack_from("<IB", event_args(seen, "check_modes_local_pos"))
    assert modes & offboard and component == px4_events.HEALTH_INDEX["local_position_estimate"]
    # ... and no ATTITUDE while the estimator settles (PX4 SIH sent none for ~30 s)
    assert not [m for m in first + seen if m.get_type() == "ATTITUDE"]
    # ... not in answer to an arm: the refusal carries only commander_arm_denied_resolve_failures
    result, at_arm = c.command_collect(ARM, 1)
    assert result == mav.MAV_RESULT_TEMPORARILY_REJECTED
    assert event_ids(at_arm) == [16910493], event_ids(at_arm)
    assert not mock.snapshot()["armed"] and not mock.snapshot()["ready"]

    # before ready: home at the local origin; the ground estimate's z wanders between -0.94 and
    # +3.60 (its horizontal drift: test_mock_px4_boot.py)
    home = c.wait("HOME_POSITION", 5)
    assert home is not None and (home.x, home.y, home.z) == (0.0, 0.0, 0.0)
    zs = [m.z for m in c.collect(1.5) if m.get_type() == "LOCAL_POSITION_NED"]
    assert zs and min(zs) >= -0.94 - 1e-6 and max(zs) <= 3.60 + 1e-6 and max(zs) - min(zs) > 0.05
    assert abs(mock.snapshot()["position"][2] - mock.ground_z) < 1e-6  # the vehicle itself stays put

    # ready: home where the vehicle stands, a clean report, arming allowed
    end = time.monotonic() + 10
    while time.monotonic() < end and mock.snapshot()["t"] < 12.2:
        time.sleep(0.1)
    assert mock.snapshot()["ready"]
    home = c.wait("HOME_POSITION", 5, lambda m: m.z != 0.0)
    assert home is not None and abs(home.z - mock.ground_z) < 1e-6
    lpos = c.wait("LOCAL_POSITION_NED", 2)
    assert lpos is not None and abs(lpos.z - mock.ground_z) < 1e-6
    assert c.wait("ATTITUDE", 2) is not None  # once ready
    assert c.command(ARM, 1) == mav.MAV_RESULT_ACCEPTED


def test_forced_arming_skips_the_checks_as_px4s_does(make_mock) -> None:  # type: ignore[no-untyped-def]
    _, c = make_mock("px4", px4_ready_s=60.0)
    assert c.command(ARM, 1, 21196) == mav.MAV_RESULT_ACCEPTED  # Commander: forced skips preflight checks


def test_statustext_flavour_says_why_in_text(make_mock) -> None:  # type: ignore[no-untyped-def]
    _, c = make_mock("px4", px4_ready_s=60.0, px4_statustext=True)
    result, seen = c.command_collect(ARM, 1)
    texts = [m.text for m in seen if m.get_type() == "STATUSTEXT"]
    assert result == mav.MAV_RESULT_TEMPORARILY_REJECTED
    assert any(t.startswith("Arming denied: Resolve system health failures") for t in texts)  # 50 chars
    assert not event_ids(seen)


def test_ready_delay_default_and_flag() -> None:
    from sitl_mock import px4

    assert 36.0 <= px4.DEFAULT_READY_S <= 37.0 or px4.DEFAULT_READY_S == 0.0  # tests patch it to 0
    assert build_parser().parse_args(["--px4-ready-after", "5"]).px4_ready_s == 5.0
    assert build_parser().parse_args([]).px4_ready_s is None
    from sitl_mock import MockConfig

    with pytest.raises(ValueError, match="px4_ready_s"):
        MockAutopilot(MockConfig(px4_ready_s=-1.0))


class Ftp:
    """A MAVLink FTP client written from the FTP service description, over pymavlink."""

    def __init__(self, c: Client) -> None:
        self.c = c
        self.seq = 0

    def request(self, opcode: int, session: int = 0, offset: int = 0, data: bytes = b"",
                size: int | None = None) -> list[tuple[int, int, int, int, bytes]]:
        """Send one request; every answer to it: (opcode, req_opcode, offset, burst_complete, data)."""
        self.seq += 1
        n = len(data) if size is None else size
        payload = (HEADER.pack(self.seq, session, opcode, n, 0, 0, 0, offset) + data).ljust(251, b"\0")
        self.c.drain()
        self.c.mav.file_transfer_protocol_send(0, 1, 1, list(payload))
        out = []
        for m in self.c.collect(1.0):
            if m.get_type() != "FILE_TRANSFER_PROTOCOL":
                continue
            raw = bytes(m.payload)
            seq, _, op, size_, req, burst, _, at = HEADER.unpack_from(raw)
            assert seq >= self.seq + 1
            out.append((op, req, at, burst, raw[12:12 + size_]))
            if op != 128 or opcode != 15 or burst:
                break
        return out

    def read(self, path: str, burst: bool = False) -> bytes:
        [(op, req, _, _, data)] = self.request(4, data=path.encode())
        assert (op, req) == (128, 4), data
        size = struct.unpack("<I", data)[0]
        content = bytearray()
        while len(content) < size:
            answers = self.request(15 if burst else 5, offset=len(content), size=239)
            for op, _, at, _, chunk in answers:
                assert op == 128 and at == len(content)
                content += chunk
        assert self.request(1) [0][0] == 128
        return bytes(content)


def test_metadata_served_as_px4_serves_it(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("px4")
    result, seen = c.command_collect(mav.MAV_CMD_REQUEST_MESSAGE, 397)  # PX4 answers before its ACK
    assert result == mav.MAV_RESULT_ACCEPTED
    # read from the frame with the C header's layout (time_boot_ms 0, file_crc 4, uri 8, 108 bytes)
    [buf] = [bytes(m.get_msgbuf()) for m in seen if int.from_bytes(bytes(m.get_msgbuf())[7:10], "little") == 397]
    raw = buf[10:10 + buf[1]].ljust(108, b"\0")
    _, file_crc = struct.unpack_from("<II", raw)
    uri = raw[8:].split(b"\0", 1)[0].decode()
    assert uri == "mftp://etc/extras/component_general.json.xz"

    ftp = Ftp(c)
    general_raw = lzma.decompress(ftp.read(uri.removeprefix("mftp://")))
    assert file_crc == zlib.crc32(general_raw, 0xFFFFFFFF) ^ 0xFFFFFFFF  # PX4's CRC32: init 0, no final xor
    general = json.loads(general_raw)
    assert general["version"] == 1
    [events_type] = [t for t in general["metadataTypes"] if t["type"] == 4]  # COMP_METADATA_TYPE_EVENTS
    assert events_type["uri"] == "mftp://etc/extras/all_events.json.xz"
    events_raw = lzma.decompress(ftp.read("/etc/extras/all_events.json.xz", burst=True))
    assert events_type["fileCrc"] == zlib.crc32(events_raw, 0xFFFFFFFF) ^ 0xFFFFFFFF
    comp = json.loads(events_raw)["components"]["1"]
    described = {int(k) | (1 << 24): e for g in comp["event_groups"].values() for k, e in g["events"].items()}
    assert set(px4_events.IDS.values()) <= set(described)  # every event the mock emits
    assert described[16910493]["message"] == "Arming denied: Resolve system health failures first"
    assert described[px4_events.IDS["commander_armed_by"]]["arguments"] == [
        {"type": "px4::enums::arm_disarm_reason_t", "name": "reason"}]
    assert comp["enums"]["arm_disarm_reason_t"]["entries"]["4"]["description"] == "external command"

    # PX4's refusals: unknown file, a second session, reads without a session, past the end
    [(op, _, _, _, err)] = ftp.request(4, data=b"etc/extras/nothing.json")
    assert (op, err[0]) == (129, 10)  # NAK FileNotFound
    assert ftp.request(4, data=b"etc/extras/all_events.json.xz")[0][0] == 128
    [(op, _, _, _, err)] = ftp.request(4, data=b"etc/extras/all_events.json.xz")
    assert (op, err[0]) == (129, 5)  # NAK NoSessionsAvailable: PX4 has one
    [(op, _, _, _, err)] = ftp.request(5, offset=10**7, size=239)
    assert (op, err[0]) == (129, 6)  # NAK EOF
    ftp.request(1)
    [(op, _, _, _, err)] = ftp.request(5, offset=0, size=239)
    assert (op, err[0]) == (129, 4)  # NAK InvalidSession
    assert mock.px4 is not None and mock.px4.ftp.opened == 3
