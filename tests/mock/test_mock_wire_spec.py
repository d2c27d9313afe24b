"""The mock's own MAVLink encoding and signing, checked against MAVLink's published definitions.

Independent of both the mock's and the companion's code: the expected layouts are those of the
C headers generated from MAVLink's message_definitions (c_library_v2 mavlink_msg_event.h:
MAVLINK_MSG_ID_EVENT_LEN 53, CRC 160, offsets id 0, event_time_boot_ms 4, sequence 8,
destination_component 10, destination_system 11, log_levels 12, arguments 13;
mavlink_msg_component_metadata.h: LEN 108, CRC 182, time_boot_ms 0, file_crc 4, uri 8), the
checksum is computed here from the serialization guide, and the signature from the signing
guide with hashlib (https://mavlink.io/en/guide/message_signing.html); the signed frame
`RUST_HEARTBEAT_SIGNED` is rust-mavlink's test vector (tests/signing.rs, tests/test_shared.rs).
"""

from __future__ import annotations

import hashlib
import socket
import struct
import time
from pathlib import Path

import pytest
from pymavlink.dialects.v20 import common as mav

from sitl_mock import MockAutopilot, MockConfig, mavwire
from sitl_mock import events as px4_events
from sitl_mock.signing import read_signing_key
from sitl_mock.transport import new_parser

RUST_KEY = bytes([0x00, 0x01, 0xF2, 0xE3, 0xD4, 0xC5, 0xB6, 0xA7, 0x98, 0x00, 0x70, 0x76, 0x34, 0x32, 0x00, 0x16,
                  0x22, 0x42, 0x00, 0xCC, 0xFF, 0x7A, 0x00, 0x52, 0x75, 0x73, 0x74, 0x00, 0x4D, 0x41, 0x56, 0xB3])
RUST_HEARTBEAT_SIGNED = bytes([
    0xFD, 0x09, 0x01, 0x00, 239, 1, 2, 0x00, 0x00, 0x00,  # header: seq 239, sys 1, comp 2, HEARTBEAT
    0x05, 0x00, 0x00, 0x00, 0x02, 0x03, 0x59, 0x03, 0x03,  # payload
    0xC9, 0x8B,  # checksum
    0x00, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF, 0xFF,  # link id, timestamp
    0x27, 0x18, 0xB1, 0x68, 0xCC, 0xF5,  # signature
])


def crc16(data: bytes) -> int:
    """X.25 / CRC-16/MCRF4XX, written from the serialization guide (not the mock's)."""
    crc = 0xFFFF
    for b in data:
        crc ^= b
        for _ in range(8):
            crc = (crc >> 1) ^ 0x8408 if crc & 1 else crc >> 1
    return crc


def frame_ok(frame: bytes, crc_extra: int) -> bool:
    n = frame[1]
    body = frame[1:10 + n]
    return struct.unpack_from("<H", frame, 10 + n)[0] == crc16(body + bytes([crc_extra]))


def signed_frame(key: bytes, msg_id: int, payload: bytes, crc_extra: int, seq: int = 0, sysid: int = 255,
                 compid: int = 190, link_id: int = 0, timestamp: int | None = None) -> bytes:
    """A MAVLink 2 frame signed as the signing guide says."""
    header = bytes([0xFD, len(payload), 0x01, 0x00, seq, sysid, compid]) + msg_id.to_bytes(3, "little")
    crc = crc16(header[1:] + payload + bytes([crc_extra]))
    body = header + payload + struct.pack("<H", crc)
    if timestamp is None:  # 10 us units since 2015-01-01
        timestamp = int((time.time() - 1420070400) * 100000)
    tail = bytes([link_id]) + timestamp.to_bytes(6, "little")
    return body + tail + hashlib.sha256(key + body + tail).digest()[:6]


@pytest.mark.parametrize(("definition", "length", "crc_extra", "offsets"), [
    (mavwire.EVENT, 53, 160, {"id": 0, "event_time_boot_ms": 4, "sequence": 8, "destination_component": 10,
                              "destination_system": 11, "log_levels": 12, "arguments": 13}),
    (mavwire.COMPONENT_METADATA, 108, 182, {"time_boot_ms": 0, "file_crc": 4, "uri": 8}),
])
def test_layout_and_crc_extra_match_the_published_headers(definition: mavwire.MessageDef, length: int,
                                                          crc_extra: int, offsets: dict[str, int]) -> None:
    assert (definition.length, definition.crc_extra) == (length, crc_extra)
    at, got = 0, {}
    for f in definition.wire_fields:
        got[f.name] = at
        at += {"uint32_t": 4, "uint16_t": 2}.get(f.type, 1) * max(1, f.array)
    assert got == offsets


def test_event_the_mock_sends_has_the_spec_layout_and_checksum(tmp_path: Path) -> None:
    """An arming refusal before PX4 is ready and the arming-check reports (every second here),
    caught as raw datagrams."""
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"], px4_ready_s=60.0,
                                    px4_report_every_s=1.0, log_path=str(tmp_path / "f.jsonl"))).start()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(0.2)
    try:
        sender = mav.MAVLink(None, srcSystem=255, srcComponent=190)
        addr = ("127.0.0.1", mock.addresses[0][1])
        sock.sendto(sender.heartbeat_encode(6, 8, 0, 0, 0).pack(sender), addr)
        sock.sendto(sender.command_long_encode(1, 1, mav.MAV_CMD_COMPONENT_ARM_DISARM, 0, 1, 0, 0, 0, 0, 0, 0)
                    .pack(sender), addr)
        events: list[bytes] = []
        end = time.monotonic() + 3.0
        def refused() -> bool:
            return any(int.from_bytes(f[10:14], "little") == 16910493 for f in events)

        while time.monotonic() < end and not (len(events) >= 5 and refused()):
            try:
                data = sock.recv(2048)
            except TimeoutError:
                continue
            if data[0] == 0xFD and int.from_bytes(data[7:10], "little") == 410:
                events.append(data)
    finally:
        sock.close()
        mock.stop()
    assert len(events) >= 4
    for frame in events:
        assert frame_ok(frame, 160)
        payload = frame[10:10 + frame[1]].ljust(53, b"\0")  # MAVLink 2 trims trailing zeros
        event_id, _, _, dcomp, dsys, _ = struct.unpack_from("<IIHBBB", payload)
        assert event_id >> 24 == 1 and (dcomp, dsys) == (0, 0)
    ids = [struct.unpack_from("<I", f, 10)[0] for f in events]
    assert 16910493 in ids  # commander_arm_denied_resolve_failures, as measured on PX4 1.15
    assert {25948424, 30612409, 27825120} <= set(ids)  # PX4's reasons and summary (autopilot-facts.md; vert_vel measured)
    denied = events[ids.index(16910493)]
    last = denied[10:10 + denied[1]].ljust(53, b"\0")
    assert last[12] == (6 << 4) | 2  # external CRITICAL, internal INFO (Commander.cpp arm())


def test_signing_accepts_the_published_vector_and_rejects_a_changed_signature() -> None:
    parser = new_parser(RUST_KEY)
    msgs = parser.parse_buffer(RUST_HEARTBEAT_SIGNED) or []
    assert [m.get_type() for m in msgs] == ["HEARTBEAT"] and parser.signing.badsig_count == 0
    bad = bytearray(RUST_HEARTBEAT_SIGNED)
    bad[-1] ^= 0x01
    parser = new_parser(RUST_KEY)
    parser.parse_buffer(bytes(bad))
    assert parser.signing.badsig_count == 1  # (a HEARTBEAT may still come unsigned: only commands must be signed)


def test_signature_computed_from_the_spec_matches_the_vector() -> None:
    """This file's own signer reproduces the published frame, so it can sign for the live test."""
    payload = RUST_HEARTBEAT_SIGNED[10:19]
    frame = signed_frame(RUST_KEY, 0, payload, 50, seq=239, sysid=1, compid=2, timestamp=0xFFFFFFFFFFFF)
    assert frame == RUST_HEARTBEAT_SIGNED


def test_live_mock_takes_commands_signed_per_spec_only(tmp_path: Path) -> None:
    key = bytes(range(32))
    key_file = tmp_path / "key.hex"
    key_file.write_text(key.hex() + "\n")
    assert read_signing_key(str(key_file)) == key
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"], signing_key=key,
                                    log_path=str(tmp_path / "f.jsonl"))).start()
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.settimeout(0.2)
    addr = ("127.0.0.1", mock.addresses[0][1])
    # COMMAND_LONG (76, CRC_EXTRA 152): REQUEST_MESSAGE AUTOPILOT_VERSION
    payload = struct.pack("<7fHBBB", 148, 0, 0, 0, 0, 0, 0, mav.MAV_CMD_REQUEST_MESSAGE, 1, 1, 0)

    def acked(frame: bytes) -> bool:
        sock.sendto(frame, addr)
        end = time.monotonic() + 1.5
        while time.monotonic() < end:
            try:
                data = sock.recv(2048)
            except TimeoutError:
                continue
            if data[0] == 0xFD and int.from_bytes(data[7:10], "little") == 77:  # COMMAND_ACK
                return True
        return False

    try:
        assert not acked(signed_frame(bytes(32), 76, payload, 152, seq=1))  # another key
        assert acked(signed_frame(key, 76, payload, 152, seq=2))
    finally:
        sock.close()
        mock.stop()


def test_key_files_of_the_wrong_shape_are_refused(tmp_path: Path) -> None:
    raw = tmp_path / "raw.key"
    raw.write_bytes(bytes(range(32)))
    assert read_signing_key(str(raw)) == bytes(range(32))
    short = tmp_path / "short.key"
    short.write_text("abcd")
    with pytest.raises(OSError, match=r"short\.key"):
        read_signing_key(str(short))


def test_event_ids_are_px4s() -> None:
    """The ids the facts file lists from PX4's metadata, from the mock's own hash."""
    assert px4_events.IDS["commander_arm_denied_resolve_failures"] == 16910493
    assert px4_events.IDS["check_estimator_hor_vel_not_stable"] == 25679424
    assert px4_events.IDS["check_modes_local_pos"] == 30612409
    assert px4_events.IDS["commander_arming_check_summary"] == 27825120
    assert px4_events.IDS["commander_health_summary"] == 18691879
