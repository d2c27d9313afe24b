"""The PX4 flavour does what a PX4 1.15 SITL did (issue 15), with pymavlink as the client:
the ground below the local origin (home, EKF origin and takeoff to match), EVENT instead of
STATUSTEXT, boot and post-disarm modes, the no-RC offboard-loss fallback and its re-entry."""

from __future__ import annotations

import math
import struct
import time
from typing import Any

import pytest
from mockkit import CUSTOM, POS_ONLY, Client, Streamer, events, records, wait_for
from pymavlink import mavutil
from pymavlink.dialects.v20 import all as mav_all
from pymavlink.dialects.v20 import common as mav

from companion.wire import dialect
from sitl_mock import FaultSpec, MockAutopilot
from sitl_mock.__main__ import build_parser, main

OFFBOARD = (CUSTOM, 6, 0)
ACCEPTED, TEMP_REJ = mav.MAV_RESULT_ACCEPTED, mav.MAV_RESULT_TEMPORARILY_REJECTED


def request(c: Client, msg_id: int, kind: str) -> Any:
    """REQUEST_MESSAGE; the message it brings (sent before or after the ACK)."""
    result, seen = c.command_collect(mav.MAV_CMD_REQUEST_MESSAGE, msg_id)
    assert result == ACCEPTED
    got = [m for m in seen if m.get_type() == kind]
    return got[-1] if got else c.wait(kind)


def hover(mock: MockAutopilot, c: Client, above_ground: float) -> Streamer:
    """OFFBOARD, armed, holding `above_ground` metres over the boot point."""
    z = mock.snapshot()["ground_z"] - above_ground
    streamer = Streamer(mock.addresses[0][1], x=0.0, y=0.0, z=z, mask=POS_ONLY)
    time.sleep(1.2 / mock.config.speed + 0.3)
    assert c.command(176, *OFFBOARD) == ACCEPTED
    assert c.command(400, 1) == ACCEPTED
    assert wait_for(lambda: abs(mock.snapshot()["position"][2] - z) < 0.15, 10)
    return streamer


def is_heartbeat(m: Any) -> bool:
    return bool(m.get_type() == "HEARTBEAT" and m.get_srcSystem() == 1)


def heartbeats(msgs: list[Any]) -> list[Any]:
    return [m for m in msgs if is_heartbeat(m)]


def disarmed(m: Any) -> bool:
    return is_heartbeat(m) and not m.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED


@pytest.mark.parametrize(("autopilot", "ground_z"), [("px4", None), ("px4", 2.5), ("ardupilot", None)])
def test_ground_home_and_ekf_origin_agree(make_mock, autopilot: str, ground_z: float | None) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock(autopilot, speed=4.0, ground_z=ground_z)
    g = mock.snapshot()["ground_z"]
    if ground_z is not None:
        assert g == ground_z
    elif autopilot == "px4":
        assert g > 0.5  # PX4's local origin is well above the ground by default
    else:
        assert g == 0.0  # ArduPilot's origin is on the ground
    lp = request(c, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, "LOCAL_POSITION_NED")
    assert lp.z == pytest.approx(g, abs=0.02)
    home = request(c, mav.MAVLINK_MSG_ID_HOME_POSITION, "HOME_POSITION")
    assert (home.x, home.y, home.z) == pytest.approx((lp.x, lp.y, lp.z), abs=0.02)
    result, seen = c.command_collect(mav.MAV_CMD_GET_HOME_POSITION)  # the older request
    assert result == ACCEPTED and any(m.get_type() == "HOME_POSITION" for m in seen)
    origin = request(c, mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, "GPS_GLOBAL_ORIGIN")
    gpi = request(c, mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT, "GLOBAL_POSITION_INT")
    # On the ground at home: AMSL altitude is home's, 0 above home; the origin is home.z above it.
    assert gpi.alt == pytest.approx(home.altitude, abs=20)
    assert gpi.relative_alt == pytest.approx(0, abs=20)
    assert origin.altitude - home.altitude == pytest.approx(home.z * 1000, abs=2)
    assert (origin.latitude, origin.longitude) == (home.latitude, home.longitude)


@pytest.mark.parametrize("how", ["amsl", "default"])
def test_takeoff_altitude_amsl_or_default_above_home(make_mock, how: str) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("px4", speed=4.0, ground_z=2.5)
    home = request(c, mav.MAVLINK_MSG_ID_HOME_POSITION, "HOME_POSITION")
    result, seen = c.command_collect(400, 1)
    assert result == ACCEPTED
    assert "commander_armed_by" in [e.name for e in events(seen)]
    assert any(m.get_type() == "HOME_POSITION" for m in seen)  # home set on arming, sent at once
    rise = 3.0 if how == "amsl" else float(mock.params["MIS_TAKEOFF_ALT"].value)
    param7 = home.altitude / 1000.0 + rise if how == "amsl" else math.nan
    result, seen = c.command_collect(mav.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, param7)
    assert result == ACCEPTED
    if how == "default":
        ev = [e for e in events(seen) if e.name == "navigator_takeoff_default_alt"]
        assert ev and ev[0].level == "INFO"
    # Takeoff done: PX4 switches to Hold (AUTO.LOITER).
    msgs = c.collect(10, until=lambda m: is_heartbeat(m) and mavutil.mode_string_v10(m) == "LOITER")
    assert "commander_takeoff_detected" in [e.name for e in events(msgs)]
    lp = c.wait("LOCAL_POSITION_NED")
    assert lp.z == pytest.approx(home.z - rise, abs=0.15)
    assert c.wait("GLOBAL_POSITION_INT").relative_alt == pytest.approx(rise * 1000, abs=150)


def test_reports_are_events_and_refusals_temporarily_rejected(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("px4", speed=4.0, faults=FaultSpec(reject_arming=True))
    everything: list[Any] = []
    result, seen = c.command_collect(400, 1)
    everything += seen
    assert result == TEMP_REJ
    denial = events(seen)
    assert [e.name for e in denial] == ["check_rc_dl_no_dllink"] and denial[0].level == "ERROR"
    mock.reject_arming = False
    result, seen = c.command_collect(400, 1)
    everything += seen
    assert result == ACCEPTED
    armed = [m for m in seen if m.get_type() == "EVENT" and dialect.decode_event(m).name == "commander_armed_by"]
    assert armed and dialect.event_arguments(armed[0])[0] == 4  # arm_disarm_reason_t command_external
    result, seen = c.command_collect(400, 0)
    everything += seen + c.collect(0.5)
    assert result == ACCEPTED
    assert "commander_disarmed_by" in [e.name for e in events(everything)]
    assert not [m for m in everything if m.get_type() == "STATUSTEXT"]
    seqs = [m.sequence for m in everything if m.get_type() == "EVENT"]
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs)))  # one sequence per component
    # A mode PX4 cannot enter now: refused, with the reason as events.
    result, seen = c.command_collect(176, *OFFBOARD)
    assert result == TEMP_REJ
    assert {"commander_modeswitch_not_avail", "check_modes_offboard_no_signal"} <= {e.name for e in events(seen)}


def test_statustext_option_for_older_px4(make_mock) -> None:  # type: ignore[no-untyped-def]
    _mock, c = make_mock("px4", speed=4.0, px4_statustext=True, faults=FaultSpec(reject_arming=True))
    result, seen = c.command_collect(400, 1)
    seen += c.collect(0.3)
    assert result == TEMP_REJ
    assert any(m.get_type() == "STATUSTEXT" and "Arming denied" in m.text for m in seen)
    assert not events(seen)


def test_event_wire_format_signed_and_in_every_dialect() -> None:
    dialect.install()
    dialect.install()  # idempotent
    # What MAVLink's generated C headers say (MAVLINK_MSG_ID_EVENT_CRC, _LEN): other
    # implementations (PX4, MAVSDK) accept only this.
    cls = mav.mavlink_map[dialect.MSG_ID_EVENT]
    assert (dialect.CRC_EXTRA, cls.unpacker.size) == (160, 53)
    key = bytes(range(32))
    sender = mav.MAVLink(None, srcSystem=1, srcComponent=1)
    sender.signing.secret_key, sender.signing.sign_outgoing, sender.signing.link_id = key, True, 1
    event_id = dialect.PX4_EVENT_IDS["commander_failsafe_enter_generic"]
    args = struct.pack("<IB", 6 << 16, 6)
    msg = dialect.event_encode(sender, event_id, "CRITICAL", internal_level="WARNING", sequence=7,
                               time_boot_ms=1234, arguments=args)
    data = msg.pack(sender)
    for module in (mav, mav_all):
        receiver = module.MAVLink(None)
        receiver.signing.secret_key = key
        got = receiver.parse_char(bytearray(data))
        assert got is not None and got.get_type() == "EVENT" and got._signed
        assert dialect.decode_event(got) == (event_id, "CRITICAL", "commander_failsafe_enter_generic")
        assert (got.log_levels >> 4, got.sequence, got.event_time_boot_ms) == (4, 7, 1234)
        assert dialect.event_arguments(got)[:5] == args
    corrupt = bytearray(data)
    corrupt[12] ^= 0xFF
    with pytest.raises(mav.MAVError):
        mav.MAVLink(None).decode(corrupt)
    assert all(i >> 24 == 1 for i in dialect.PX4_EVENTS)  # PX4: the autopilot component's namespace
    with pytest.raises(ValueError, match="at most 40"):
        dialect.event_encode(sender, event_id, "INFO", sequence=0, time_boot_ms=0, arguments=bytes(41))


@pytest.mark.parametrize("how", ["setpoints", "land_command"])
def test_after_landing_and_auto_disarm_offboard_is_reported(make_mock, how: str) -> None:  # type: ignore[no-untyped-def]
    """PX4 goes back to the last user mode one can arm in: OFFBOARD, not LAND."""
    mock, c = make_mock("px4", speed=4.0)
    assert c.mode() == "LOITER"  # PX4 boots in AUTO.LOITER
    streamer = hover(mock, c, 1.5)
    try:
        if how == "setpoints":
            streamer.setpoint = {**streamer.setpoint, "z": mock.snapshot()["ground_z"]}
        else:
            assert c.command(mav.MAV_CMD_NAV_LAND) == ACCEPTED
            assert mock.snapshot()["mode"] == "LAND"
        msgs = c.collect(12, until=disarmed)
    finally:
        streamer.stop()
    assert msgs and disarmed(msgs[-1])
    assert mavutil.mode_string_v10(msgs[-1]) == "OFFBOARD"
    names = [e.name for e in events(msgs)]
    assert "commander_landing_detected" in names
    off = [m for m in msgs if m.get_type() == "EVENT" and dialect.decode_event(m).name == "commander_disarmed_by"]
    assert off and dialect.event_arguments(off[0])[0] == 7  # auto_disarm_land
    assert c.mode() == "OFFBOARD"


def test_offboard_loss_without_rc_returns_lands_and_disarms(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("px4", speed=4.0)
    assert mock.params["COM_OBL_RC_ACT"].value == 0  # PX4's default: Position mode
    streamer = hover(mock, c, 1.5)
    streamer.stop()
    msgs = c.collect(15, until=disarmed)
    assert msgs and disarmed(msgs[-1])
    modes = [mavutil.mode_string_v10(m) for m in heartbeats(msgs)]
    # Position mode cannot run without RC: PX4's fallback ends in Return, which lands at home.
    assert "RTL" in modes and modes[-1] == "OFFBOARD"
    fs = [m for m in msgs if m.get_type() == "EVENT" and dialect.decode_event(m).name == "commander_failsafe_enter_generic"]
    assert fs and dialect.decode_event(fs[0]).level == "CRITICAL"
    assert struct.unpack("<IB", dialect.event_arguments(fs[0])[:5]) == (6 << 16, 6)  # user mode OFFBOARD; RTL
    last_sp = max(r["t"] for r in records(mock, "setpoint") if r["valid"])
    change = [r for r in records(mock, "mode") if r["to"] == "RTL" and r["reason"] == "failsafe"]
    assert len(change) == 1 and change[0]["t"] - last_sp == pytest.approx(1.0, abs=0.2)  # COM_OF_LOSS_T
    snap = mock.snapshot()
    assert snap["landed"] and not snap["armed"]
    assert snap["position"][2] == pytest.approx(snap["ground_z"], abs=0.05)


def test_offboard_reentry_while_armed_and_offboard_is_the_users_mode(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("px4", speed=4.0)
    streamer = hover(mock, c, 2.0)
    z = streamer.setpoint["z"]
    streamer.stop()
    assert wait_for(lambda: mock.snapshot()["mode"] == "RTL", 3)
    for _ in range(2):  # a stalled sender's last setpoints
        c.setpoint(0.0, 0.0, z, mask=POS_ONLY)
        time.sleep(0.02)
    hb = c.wait("HEARTBEAT", cond=lambda m: m.get_srcSystem() == 1 and mavutil.mode_string_v10(m) == "OFFBOARD")
    assert hb is not None and hb.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED
    assert wait_for(lambda: mock.snapshot()["mode"] == "RTL", 3)  # and lost again
    failsafes = [r for r in records(mock, "mode") if r["to"] == "RTL" and r["reason"] == "failsafe"]
    assert len(failsafes) == 2
    last_sp = max(r["t"] for r in records(mock, "setpoint") if r["valid"])
    assert failsafes[1]["t"] - last_sp == pytest.approx(1.0, abs=0.2)
    assert any(r["reason"] == "offboard signal regained" for r in records(mock, "mode"))
    # Once the user picks another mode, setpoints no longer bring OFFBOARD back.
    assert c.command(176, CUSTOM, 4, 3) == ACCEPTED
    for _ in range(3):
        c.setpoint(0.0, 0.0, z, mask=POS_ONLY)
        time.sleep(0.02)
    time.sleep(0.2)
    assert mock.snapshot()["mode"] == "LOITER" and mock.snapshot()["user_mode"] == "LOITER"


def test_cli_flags() -> None:
    args = build_parser().parse_args(["--ground-z", "0.5", "--px4-statustext"])
    assert args.ground_z == 0.5 and args.px4_statustext
    defaults = build_parser().parse_args([])
    assert defaults.ground_z is None and not defaults.px4_statustext
    assert main(["--ground-z", "nan", "--endpoint", "udpin:127.0.0.1:0"]) == 2
