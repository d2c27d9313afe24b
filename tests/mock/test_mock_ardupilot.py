"""ArduPilot Copter flavour: GUIDED rules over real MAVLink/UDP."""

from __future__ import annotations

import time

import pytest
from mockkit import CUSTOM, POS_ONLY, records, wait_for
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mav

GUIDED, LOITER, STABILIZE = 4, 5, 0
ACCEPTED, FAILED = mav.MAV_RESULT_ACCEPTED, mav.MAV_RESULT_FAILED
VEL_ONLY = 0b0000_1101_1100_0111  # ignore position, acceleration, yaw rate


def airborne(mock, c, alt: float = 3.0):  # type: ignore[no-untyped-def]
    assert c.command(176, CUSTOM, GUIDED) == ACCEPTED
    assert c.command(400, 1) == ACCEPTED
    assert c.command(22, 0, 0, 0, 0, 0, 0, alt) == ACCEPTED
    assert wait_for(lambda: abs(mock.snapshot()["position"][2] + alt) < 0.1, 10)


def test_heartbeat_and_mode_numbers(make_mock) -> None:  # type: ignore[no-untyped-def]
    _, c = make_mock("ardupilot", speed=4.0)
    hb = c.wait("HEARTBEAT", cond=lambda m: m.get_srcSystem() == 1)
    assert hb.autopilot == mav.MAV_AUTOPILOT_ARDUPILOTMEGA and mavutil.mode_string_v10(hb) == "STABILIZE"
    for num, name in [(GUIDED, "GUIDED"), (17, "BRAKE"), (9, "LAND"), (6, "RTL"), (LOITER, "LOITER")]:
        assert c.command(176, CUSTOM, num) == ACCEPTED
        assert c.wait("HEARTBEAT", cond=lambda m, n=name: mavutil.mode_string_v10(m) == n) is not None
    assert c.command(176, CUSTOM, 99) == FAILED
    c.drain()
    c.mav.set_mode_send(1, CUSTOM, GUIDED)
    ack = c.wait("COMMAND_ACK", cond=lambda m: m.command == mav.MAVLINK_MSG_ID_SET_MODE)
    assert ack is not None and ack.result == ACCEPTED


def test_takeoff_denied_unless_guided_and_armed(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=3.0)
    assert c.command(22, 0, 0, 0, 0, 0, 0, 3.0) == FAILED  # STABILIZE, disarmed
    assert c.command(400, 1) == ACCEPTED
    assert c.command(22, 0, 0, 0, 0, 0, 0, 3.0) == FAILED  # STABILIZE, armed
    assert c.command(400, 0) == ACCEPTED
    assert c.command(176, CUSTOM, GUIDED) == ACCEPTED
    assert c.command(22, 0, 0, 0, 0, 0, 0, 3.0) == FAILED  # GUIDED, disarmed
    refusals = [r for r in records(mock, "event") if r["event"] == "takeoff_refused"]
    assert len(refusals) == 3
    assert c.command(400, 1) == ACCEPTED
    # Position targets on the ground before takeoff do nothing.
    c.setpoint(x=2.0, y=0.0, z=-2.0, mask=POS_ONLY)
    assert wait_for(lambda: records(mock, "setpoint"), 2)
    assert records(mock, "setpoint")[-1]["reason"] == "landed: takeoff first"
    time.sleep(0.3)
    assert mock.snapshot()["landed"]
    assert c.command(22, 0, 0, 0, 0, 0, 0, 3.0) == ACCEPTED
    assert wait_for(lambda: abs(mock.snapshot()["position"][2] + 3.0) < 0.1, 10)
    c.setpoint(x=2.0, y=0.0, z=-3.0, mask=POS_ONLY)
    assert wait_for(lambda: abs(mock.snapshot()["position"][0] - 2.0) < 0.1, 10)


def test_targets_ignored_outside_guided(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=3.0)
    airborne(mock, c)
    assert c.command(176, CUSTOM, LOITER) == ACCEPTED
    c.setpoint(x=4.0, y=0.0, z=-3.0, mask=POS_ONLY)
    time.sleep(0.4)
    assert records(mock, "setpoint")[-1]["reason"] == "not in GUIDED"
    assert abs(mock.snapshot()["position"][0]) < 0.05


def test_unsupported_frame_stops_and_holds(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=3.0)
    airborne(mock, c)
    c.setpoint(mask=VEL_ONLY, vel=(2.0, 0.0, 0.0))
    assert wait_for(lambda: mock.snapshot()["velocity"][0] > 1.9, 5)
    c.setpoint(x=100.0, mask=POS_ONLY, frame=mav.MAV_FRAME_GLOBAL)
    assert wait_for(lambda: abs(mock.snapshot()["velocity"][0]) < 0.02, 5)
    x_stop = mock.snapshot()["position"][0]
    time.sleep(0.5)
    assert mock.snapshot()["position"][0] == pytest.approx(x_stop, abs=0.05)
    last = records(mock, "setpoint")[-1]
    assert last["applied"] and "unsupported" in last["reason"] and last["vel"] == [0.0, 0.0, 0.0]


def test_unsupported_combination_stops(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=3.0)
    airborne(mock, c)
    c.setpoint(mask=VEL_ONLY, vel=(2.0, 0.0, 0.0))
    assert wait_for(lambda: mock.snapshot()["velocity"][0] > 1.9, 5)
    c.setpoint(x=100.0, z=-3.0, mask=0b0000_1100_0011_1000)  # position + acceleration
    assert wait_for(lambda: abs(mock.snapshot()["velocity"][0]) < 0.02, 5)
    assert mock.snapshot()["position"][0] < 20.0


def test_group_masking(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=3.0)
    airborne(mock, c)
    # Only the x-position bit set: ArduPilot ignores all of position and flies the velocity.
    c.setpoint(x=0.0, y=0.0, z=-3.0, mask=0b0000_1101_1100_0001, vel=(0.0, 1.0, 0.0))
    assert wait_for(lambda: mock.snapshot()["position"][1] > 1.0, 5)
    last = records(mock, "setpoint")[-1]
    assert last["pos"] == [None, None, None] and last["vel"] == [0.0, 1.0, 0.0]


def test_guid_timeout_zeroes_velocity_keeps_position(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=3.0)
    airborne(mock, c)
    c.setpoint(mask=VEL_ONLY, vel=(1.0, 0.0, 0.0))
    assert wait_for(lambda: any(r["event"] == "guided_timeout" for r in records(mock, "event")), 5)
    last_sp = records(mock, "setpoint")[-1]["t"]
    timeout = next(r for r in records(mock, "event") if r["event"] == "guided_timeout")
    assert timeout["t"] - last_sp == pytest.approx(3.0, abs=0.05)
    assert mock.snapshot()["position"][0] > 2.0  # it flew at 1 m/s until the timeout
    assert wait_for(lambda: abs(mock.snapshot()["velocity"][0]) < 0.02, 5)
    # Position + velocity target: the target moves on along its velocity until the timeout
    # (AC_PosControl::input_pos_vel_accel_xy writes the projected target back into GUIDED's),
    # then its position is held: 5.0 + 0.5 m/s x 3 s.
    c.setpoint(x=5.0, y=1.0, z=-3.0, mask=0b0000_1101_1100_0000, vel=(0.5, 0.0, 0.0))
    assert wait_for(lambda: sum(r["event"] == "guided_timeout" for r in records(mock, "event")) == 2, 6)
    assert wait_for(lambda: abs(mock.snapshot()["position"][0] - 6.5) < 0.05, 5)
    assert mock.snapshot()["position"][1] == pytest.approx(1.0, abs=0.05)


def test_auto_disarm_without_takeoff(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=8.0, params={"DISARM_DELAY": 2})
    assert c.command(176, CUSTOM, GUIDED) == ACCEPTED
    assert c.command(400, 1) == ACCEPTED
    assert wait_for(lambda: not mock.snapshot()["armed"], 3)
    ev = [r for r in records(mock, "event") if r["event"] in ("armed", "disarmed")]
    assert ev[-1]["t"] - ev[-2]["t"] == pytest.approx(2.0, abs=0.05)


def test_land_then_disarm(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=4.0)
    airborne(mock, c, alt=1.5)
    assert c.command(21) == ACCEPTED
    assert wait_for(lambda: not mock.snapshot()["armed"], 8)
    assert mock.snapshot()["landed"] and mock.snapshot()["position"][2] == 0.0
