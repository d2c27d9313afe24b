"""Telemetry on a fresh link, as stock autopilots send it, with pymavlink as the client.

ArduPilot: HEARTBEAT (and STATUSTEXT) only until streams are requested (REQUEST_DATA_STREAM
groups, SET_MESSAGE_INTERVAL per message, or MAV1_* rate parameters at boot); then at the
requested rates; EXTENDED_SYS_STATE on request only; a reboot forgets requests. PX4: what
its Onboard mode streams, unasked; PX4 SITL's ports (listen 14580, send to 14540).
"""

from __future__ import annotations

import time
from typing import Any

import numpy as np
from mockkit import Client, free_udp_port
from pymavlink.dialects.v20 import common as mav

from sitl_mock import MockAutopilot, MockConfig
from sitl_mock.transport import parse_endpoint

TELEMETRY = ("LOCAL_POSITION_NED", "ATTITUDE", "EXTENDED_SYS_STATE", "GLOBAL_POSITION_INT", "SYS_STATUS")


def collect(c: Client, seconds: float) -> dict[str, list[Any]]:
    """Every message from the autopilot (sysid 1) for `seconds` of wall time."""
    out: dict[str, list[Any]] = {}
    end = time.monotonic() + seconds
    while time.monotonic() < end:
        m = c.conn.recv_match(blocking=True, timeout=0.05)
        if m is not None and m.get_srcSystem() == 1:
            out.setdefault(m.get_type(), []).append(m)
    return out


def rate(msgs: list[Any]) -> float:
    """Messages per simulated second, from their own time_boot_ms stamps."""
    t = np.array([m.time_boot_ms for m in msgs], dtype=float) / 1000.0
    return float((len(t) - 1) / (t[-1] - t[0]))


def test_ardupilot_sends_only_heartbeat_until_asked(make_mock) -> None:  # type: ignore[no-untyped-def]
    _, c = make_mock("ardupilot", speed=4.0)
    got = collect(c, 1.0)  # 4 simulated seconds
    assert len(got.get("HEARTBEAT", [])) >= 2
    # ArduPilot announces home and the EKF origin once when home is set (AP_AHRS::set_home sends
    # MSG_HOME and MSG_ORIGIN): one-off messages, not streams; nothing else unasked
    assert set(got) <= {"HEARTBEAT", "STATUSTEXT", "HOME_POSITION", "GPS_GLOBAL_ORIGIN"}, sorted(got)
    assert len(got.get("HOME_POSITION", [])) <= 1 and len(got.get("GPS_GLOBAL_ORIGIN", [])) <= 1, sorted(got)


def test_ardupilot_streams_groups_at_the_requested_rate(make_mock) -> None:  # type: ignore[no-untyped-def]
    _, c = make_mock("ardupilot", speed=4.0)
    c.mav.request_data_stream_send(1, 1, mav.MAV_DATA_STREAM_POSITION, 10, 1)
    c.mav.request_data_stream_send(1, 1, mav.MAV_DATA_STREAM_EXTRA1, 4, 1)
    time.sleep(0.2)
    c.drain()
    got = collect(c, 1.5)
    assert 9.0 <= rate(got["LOCAL_POSITION_NED"]) <= 11.0
    assert 3.6 <= rate(got["ATTITUDE"]) <= 4.4
    assert "GLOBAL_POSITION_INT" in got  # same group as LOCAL_POSITION_NED
    assert "EXTENDED_SYS_STATE" not in got  # in no group: on request only
    # stopped again
    c.mav.request_data_stream_send(1, 1, mav.MAV_DATA_STREAM_POSITION, 0, 0)
    time.sleep(0.2)
    c.drain()
    assert "LOCAL_POSITION_NED" not in collect(c, 0.5)


def test_ardupilot_extended_sys_state_by_message_interval(make_mock) -> None:  # type: ignore[no-untyped-def]
    _, c = make_mock("ardupilot", speed=4.0)
    assert c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE, 500_000) \
        == mav.MAV_RESULT_ACCEPTED
    got = collect(c, 1.5)
    assert len(got["EXTENDED_SYS_STATE"]) >= 6  # 2 Hz over 6 simulated seconds
    assert got["EXTENDED_SYS_STATE"][-1].landed_state == mav.MAV_LANDED_STATE_ON_GROUND
    assert "LOCAL_POSITION_NED" not in got


def test_ardupilot_rate_parameters_at_boot_and_requests_lost_on_reboot(make_mock) -> None:  # type: ignore[no-untyped-def]
    _, c = make_mock("ardupilot", speed=4.0, params={"MAV1_POSITION": 5})
    got = collect(c, 1.0)
    assert 4.5 <= rate(got["LOCAL_POSITION_NED"]) <= 5.5 and "ATTITUDE" not in got
    c.mav.request_data_stream_send(1, 1, mav.MAV_DATA_STREAM_EXTRA1, 10, 1)
    assert "ATTITUDE" in collect(c, 0.5)
    assert c.command(mav.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN, 1) == mav.MAV_RESULT_ACCEPTED
    time.sleep(1.0)  # 4 simulated seconds: rebooted
    c.drain()
    got = collect(c, 1.0)
    assert "HEARTBEAT" in got and "LOCAL_POSITION_NED" in got and "ATTITUDE" not in got


def test_px4_streams_its_onboard_set_unasked(make_mock) -> None:  # type: ignore[no-untyped-def]
    _, c = make_mock("px4", speed=2.0)
    got = collect(c, 1.0)
    for name in TELEMETRY:
        assert name in got, name
    assert rate(got["LOCAL_POSITION_NED"]) >= 25.0
    # and ignores the legacy request (PX4 has no stream groups)
    c.mav.request_data_stream_send(1, 1, mav.MAV_DATA_STREAM_ALL, 0, 0)
    time.sleep(0.2)
    c.drain()
    assert "LOCAL_POSITION_NED" in collect(c, 0.3)


def test_px4_sitl_ports(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """Bound to its own port, sending to the client's: as PX4 SITL's 14580 -> 14540 (here on
    free ports); the client listens (udpin) and its answers reach the mock."""
    ep = parse_endpoint("udpout:127.0.0.1:14540@0.0.0.0:14580")
    assert (ep.kind, ep.port, ep.bind) == ("udpout", 14540, ("0.0.0.0", 14580))
    listen, bind = free_udp_port(), free_udp_port()
    from pymavlink import mavutil

    client = mavutil.mavlink_connection(f"udpin:127.0.0.1:{listen}", source_system=255, source_component=190)
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=[f"udpout:127.0.0.1:{listen}@127.0.0.1:{bind}"],
                                    log_path=str(tmp_path / "f.jsonl"))).start()
    try:
        hb = client.recv_match(type="HEARTBEAT", blocking=True, timeout=5)
        assert hb is not None and hb.get_srcSystem() == 1
        assert tuple(mock.addresses[0]) == ("127.0.0.1", bind)  # sent from the bound port
        client.mav.command_long_send(1, 1, mav.MAV_CMD_REQUEST_MESSAGE, 0,
                                     mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION, 0, 0, 0, 0, 0, 0)
        ack = client.recv_match(type="COMMAND_ACK", blocking=True, timeout=5)
        assert ack is not None and ack.result == mav.MAV_RESULT_ACCEPTED
    finally:
        mock.stop()
        client.close()
