"""ArduPilot flavour as strict as stock ArduCopter SITL (issue 20 point 2), over real MAVLink/UDP.

Each test is a rule of sitl_mock/README.md's ArduPilot list; the figures come from
/work/shared/autopilot-facts.md or ArduCopter's sources named there.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from mockkit import CUSTOM, records, wait_for
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mav

from sitl_mock import MockConfig
from sitl_mock.control import ControlClient

STABILIZE, ALT_HOLD, GUIDED, LOITER, LAND, POSHOLD, BRAKE = 0, 2, 4, 5, 9, 16, 17
ACCEPTED, FAILED = mav.MAV_RESULT_ACCEPTED, mav.MAV_RESULT_FAILED
VEL_ONLY = 0b0000_1101_1100_0111
PVA = 0b0000_1100_0000_0000  # position, velocity, acceleration; yaw


def airborne(mock, c, alt: float = 6.0) -> None:  # type: ignore[no-untyped-def]
    assert c.command(176, CUSTOM, GUIDED) == ACCEPTED
    assert c.command(400, 1) == ACCEPTED
    assert c.command(22, 0, 0, 0, 0, 0, 0, alt) == ACCEPTED
    assert wait_for(lambda: abs(mock.snapshot()["position"][2] + alt) < 0.05
                    and abs(mock.snapshot()["velocity"][2]) < 0.05, 30)


def sim_sleep(mock, seconds: float) -> None:  # type: ignore[no-untyped-def]
    """Sleep `seconds` of simulated time."""
    t0 = mock.snapshot()["t"]
    while mock.snapshot()["t"] - t0 < seconds:
        time.sleep(0.02)


def vertical_speed_after(mock, seconds: float) -> float:  # type: ignore[no-untyped-def]
    sim_sleep(mock, seconds)
    return float(mock.snapshot()["velocity"][2])


def test_defaults_are_stock_sitl() -> None:
    cfg = MockConfig(autopilot="ardupilot")
    # SITL without a transmitter sends throttle 1000 (AP_RCProtocol_UDP); origin ~43 s after
    # SITL's start (measured), spool-up 3.0 s (measured); shaping on.
    assert (cfg.rc_throttle, cfg.ekf_origin_delay_s, cfg.spool_up_s, cfg.shaping) == (1000, 40.0, 3.0, True)
    assert cfg.position_after_origin_s == 22.0
    with pytest.raises(ValueError, match="rc_throttle"):
        MockConfig(autopilot="ardupilot", rc_throttle=3000).validate()
    with pytest.raises(ValueError, match="spool_up_s"):
        MockConfig(autopilot="ardupilot", spool_up_s=-1.0).validate()


@pytest.mark.parametrize("mode", [LOITER, ALT_HOLD, POSHOLD])
def test_pilot_modes_descend_with_sitls_rc_then_land_and_disarm(make_mock, mode: int) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=5.0, params={"DISARM_DELAY": 3})
    airborne(mock, c)
    assert c.command(176, CUSTOM, mode) == ACCEPTED
    # PILOT_SPEED_DN 0 -> PILOT_SPEED_UP 250 cm/s, reached at PILOT_ACCEL_Z 2.5 m/s^2.
    assert vertical_speed_after(mock, 1.8) == pytest.approx(2.5, abs=0.12)
    assert wait_for(lambda: mock.snapshot()["landed"], 10)
    landed_t = mock.snapshot()["t"]
    assert wait_for(lambda: not mock.snapshot()["armed"], 10)
    disarm = [r for r in records(mock, "event") if r["event"] == "disarmed"][-1]
    assert disarm["t"] - landed_t == pytest.approx(3.0, abs=0.3)  # DISARM_DELAY after touchdown
    assert mock.snapshot()["mode"] == mavutil.mode_mapping_acm[mode]


@pytest.mark.parametrize(("rc", "params"), [(1500, {}), (None, {"FS_THR_ENABLE": 0})])
def test_loiter_holds_at_mid_stick_or_with_no_rc_ever(make_mock, rc, params) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=5.0, rc_throttle=rc, params=params)
    airborne(mock, c)
    z0 = mock.snapshot()["position"][2]
    assert c.command(176, CUSTOM, LOITER) == ACCEPTED
    sim_sleep(mock, 8.0)
    s = mock.snapshot()
    assert s["mode"] == "LOITER" and s["armed"] and not s["rc_failsafe"]
    assert abs(s["position"][2] - z0) < 0.05 and math.hypot(*s["position"][:2]) < 0.05


def test_stabilize_with_throttle_down_falls(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=4.0)
    airborne(mock, c, alt=10.0)
    assert c.command(176, CUSTOM, STABILIZE) == ACCEPTED
    # Motors at ground idle: free fall, far faster than any controlled descent.
    assert vertical_speed_after(mock, 1.0) > 6.0
    assert wait_for(lambda: mock.snapshot()["landed"], 5)


def test_rc_loss_runs_the_throttle_failsafe(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=4.0, rc_throttle=1500, control="127.0.0.1:0")
    airborne(mock, c)
    with ControlClient(*mock.control_address) as ctl:
        assert ctl.rc(None)["ok"]
        lost_t = mock.snapshot()["t"]
        text = c.wait("STATUSTEXT", 5, lambda m: m.text.startswith("Radio Failsafe"))
        assert text is not None and text.text == "Radio Failsafe"
        ev = next(r for r in records(mock, "event") if r["event"] == "failsafe")
        assert ev["cause"] == "radio" and ev["action"] == "RTL"
        assert ev["t"] - lost_t == pytest.approx(1.0, abs=0.1)  # RC_FS_TIMEOUT
        assert wait_for(lambda: mock.snapshot()["mode"] == "RTL", 2)
        with pytest.raises(ValueError, match="throttle"):
            mock._control_request({"cmd": "rc", "throttle": "low"})


def test_rc_failsafe_continues_guided_only_with_fs_options(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=4.0, rc_throttle=1500, control="127.0.0.1:0",
                        params={"FS_OPTIONS": 16 | 4})
    airborne(mock, c)
    with ControlClient(*mock.control_address) as ctl:
        ctl.rc(None)
        assert c.wait("STATUSTEXT", 5, lambda m: m.text == "Radio Failsafe - Continuing Guided Mode") is not None
    assert wait_for(lambda: mock.snapshot()["rc_failsafe"], 2)
    sim_sleep(mock, 2.0)
    assert mock.snapshot()["mode"] == "GUIDED"


def test_no_rc_refuses_arming_with_the_throttle_failsafe_on(make_mock) -> None:  # type: ignore[no-untyped-def]
    _, c = make_mock("ardupilot", speed=4.0, rc_throttle=None)
    assert c.command(176, CUSTOM, GUIDED) == ACCEPTED
    result, seen = c.command_collect(400, 1)
    assert result == FAILED
    assert "PreArm: Throttle below Failsafe" in [m.text for m in seen if m.get_type() == "STATUSTEXT"]


def test_no_position_before_the_ekf_origin(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=2.0, ekf_origin_delay_s=4.0)
    assert mock.snapshot()["t"] < 3.0
    # The interval request is accepted, as ArduPilot does; nothing is sent until the origin.
    assert c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 50_000) == ACCEPTED
    assert c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, 200_000) == ACCEPTED
    assert c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_ATTITUDE, 100_000) == ACCEPTED
    assert c.command(176, CUSTOM, GUIDED) == ACCEPTED  # mode changes are not checked while disarmed
    result, seen = c.command_collect(400, 1)
    assert result == FAILED
    assert "PreArm: Need Position Estimate" in [m.text for m in seen if m.get_type() == "STATUSTEXT"]
    before = c.collect(0.5)
    kinds = {m.get_type() for m in before}
    assert "ATTITUDE" in kinds and "LOCAL_POSITION_NED" not in kinds and "GPS_GLOBAL_ORIGIN" not in kinds
    assert mock.snapshot()["t"] < 4.0 and not mock.snapshot()["ekf_origin"]
    # Modes that need no position arm before the origin (mandatory_gps_checks).
    assert c.command(176, CUSTOM, STABILIZE) == ACCEPTED
    assert c.command(400, 1) == ACCEPTED
    assert c.command(400, 0) == ACCEPTED
    seen = c.collect(4.0, until=lambda m: m.get_type() == "LOCAL_POSITION_NED")
    assert seen[-1].get_type() == "LOCAL_POSITION_NED"
    assert "EKF3 IMU0 origin set" in [m.text for m in seen if m.get_type() == "STATUSTEXT"]
    first = next(r for r in records(mock, "event") if r["event"] == "ekf_origin_set")
    assert first["since_boot"] == pytest.approx(4.0, abs=0.01)
    assert c.wait("GPS_GLOBAL_ORIGIN", 2) is not None
    assert c.command(176, CUSTOM, GUIDED) == ACCEPTED
    assert c.command(400, 1) == ACCEPTED


def test_home_comes_before_the_position(make_mock) -> None:  # type: ignore[no-untyped-def]
    """Stock ArduCopter 4.6 SITL, measured 2026-12-02: HOME_POSITION and GPS_GLOBAL_ORIGIN ~22 s
    before the first LOCAL_POSITION_NED (a client that waits for home alone starts too early)."""
    mock, c = make_mock("ardupilot", speed=3.0, ekf_origin_delay_s=2.0, position_after_origin_s=4.0)
    assert c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 50_000) == ACCEPTED
    assert c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_HOME_POSITION, 200_000) == ACCEPTED
    seen = c.collect(10.0, until=lambda m: m.get_type() == "HOME_POSITION")
    assert seen and seen[-1].get_type() == "HOME_POSITION"
    t_home = mock.snapshot()["t"]
    assert "LOCAL_POSITION_NED" not in {m.get_type() for m in seen}
    seen = c.collect(10.0, until=lambda m: m.get_type() == "LOCAL_POSITION_NED")
    assert seen and seen[-1].get_type() == "LOCAL_POSITION_NED"
    t_pos = mock.snapshot()["t"]
    assert t_pos - t_home == pytest.approx(4.0, abs=0.6)
    first = next(r for r in records(mock, "event") if r["event"] == "position_estimate")
    assert first["since_origin"] == pytest.approx(4.0, abs=0.05)


def test_home_moves_to_where_it_arms_and_is_sent(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=5.0, params={"DISARM_DELAY": 1})
    # sent once when the EKF origin is set (AP_AHRS::set_home sends MSG_HOME and MSG_ORIGIN), then
    # not streamed unasked
    c.wait("HOME_POSITION", 1)
    assert c.wait("HOME_POSITION", 1.5) is None
    airborne(mock, c, alt=3.0)
    c.setpoint(x=3.0, y=2.0, z=-3.0, mask=0b0000_1101_1111_1000)
    assert wait_for(lambda: math.dist(mock.snapshot()["position"][:2], (3.0, 2.0)) < 0.05, 10)
    assert c.command(mav.MAV_CMD_NAV_LAND) == ACCEPTED
    assert wait_for(lambda: not mock.snapshot()["armed"], 15)
    # home stays where it armed (the ground estimate, moved by the default shift from the origin)
    assert mock.snapshot()["home"][:2] == pytest.approx(list(mock.config.home_shift_at_arming), abs=1e-9)
    assert c.command(176, CUSTOM, GUIDED) == ACCEPTED
    result, seen = c.command_collect(400, 1)
    assert result == ACCEPTED
    homes = [m for m in seen if m.get_type() == "HOME_POSITION"]
    homes += [m for m in [c.wait("HOME_POSITION", 1)] if m is not None]
    assert homes, "HOME_POSITION not sent at arming"
    assert (homes[0].x, homes[0].y) == (pytest.approx(3.0, abs=0.05), pytest.approx(2.0, abs=0.05))


def test_home_of_the_origin_moves_at_arming_by_the_measured_shift(make_mock) -> None:  # type: ignore[no-untyped-def]
    """Stock ArduCopter 4.6 SITL, measured 2026-12-02: home moved ~1 cm at arming (the EKF's
    estimate on the ground moved on after the origin set home); the mock's default is that
    shift, and a larger one is settable."""
    assert MockConfig(autopilot="ardupilot", endpoints=["udpin:127.0.0.1:0"]).home_shift_at_arming == (-0.011, 0.008)
    shift = np.array([0.3, -0.2, 0.0])
    _, c = make_mock("ardupilot", speed=3.0, home_shift_at_arming=(0.3, -0.2))
    result, seen = c.command_collect(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_HOME_POSITION)
    assert result == ACCEPTED
    first = next((m for m in seen if m.get_type() == "HOME_POSITION"), None) or c.wait("HOME_POSITION", 1)
    assert first is not None
    assert c.command(mav.MAV_CMD_SET_MESSAGE_INTERVAL, mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, 50_000) == ACCEPTED
    pos = c.wait("LOCAL_POSITION_NED", 2)
    assert pos is not None
    before = np.array([first.x, first.y, first.z])
    here = np.array([pos.x, pos.y, pos.z])
    assert np.allclose(here - before, shift, atol=2e-3), (before, here)
    # home was set at the origin: the two are one point until the vehicle arms
    result, seen = c.command_collect(mav.MAV_CMD_REQUEST_MESSAGE, mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)
    origin = next((m for m in seen if m.get_type() == "GPS_GLOBAL_ORIGIN"), None) or c.wait("GPS_GLOBAL_ORIGIN", 1)
    assert origin is not None and (origin.latitude, origin.longitude) == (first.latitude, first.longitude)
    assert c.command(176, CUSTOM, GUIDED) == ACCEPTED
    result, seen = c.command_collect(400, 1)
    assert result == ACCEPTED
    homes = [m for m in seen if m.get_type() == "HOME_POSITION"]
    homes += [m for m in [c.wait("HOME_POSITION", 1)] if m is not None]
    assert homes, "HOME_POSITION not sent at arming"
    after = np.array([homes[0].x, homes[0].y, homes[0].z])
    assert np.allclose(after - before, shift, atol=2e-3) and np.allclose(after, here, atol=2e-3)
    with pytest.raises(ValueError, match="home_shift_at_arming"):
        MockConfig(autopilot="ardupilot", endpoints=["udpin:127.0.0.1:0"], home_shift_at_arming=(0.0, math.nan)).validate()


def test_spool_up_before_the_climb(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=3.0)
    assert c.command(176, CUSTOM, GUIDED) == ACCEPTED
    assert c.command(400, 1) == ACCEPTED
    assert c.command(22, 0, 0, 0, 0, 0, 0, 2.0) == ACCEPTED
    assert wait_for(lambda: mock.snapshot()["position"][2] < -2.0 + 0.05, 15)
    armed_t = next(r for r in records(mock, "event") if r["event"] == "armed")["t"]
    states = [r for r in records(mock, "state") if r["t"] >= armed_t]
    climbing = next(r for r in states if r["pos"][2] < -1e-3)
    # Measured: no climb for 3.0 s; then the shaped climb starts at PSC_JERK_Z (1 cm in ~0.3 s).
    assert 3.0 <= climbing["t"] - armed_t < 3.5
    two_m = next(r for r in states if r["pos"][2] <= -2.0 + 0.05)
    # Measured on SITL: 2 m 5.7 s after arming (WPNAV_SPEED_UP 2.5, WPNAV_ACCEL_Z 1.0 shape the climb).
    assert 4.5 < two_m["t"] - armed_t < 7.0, two_m["t"] - armed_t


def test_brake_stops_and_holds_until_a_mode_change(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=5.0)
    airborne(mock, c)
    c.setpoint(mask=VEL_ONLY, vel=(4.0, 0.0, 0.0))
    assert wait_for(lambda: mock.snapshot()["velocity"][0] > 3.95, 10)
    x_entry = mock.snapshot()["position"][0]
    assert c.command(176, CUSTOM, BRAKE) == ACCEPTED
    assert wait_for(lambda: abs(mock.snapshot()["velocity"][0]) < 0.02, 10)
    sim_sleep(mock, 1.0)
    stop = mock.snapshot()["position"]
    # It stops where its deceleration ends (BRAKE_MODE_DECEL_RATE 7.5 m/s^2: >= 1.07 m from
    # 4 m/s), and does not fly back to where BRAKE began.
    assert stop[0] - x_entry > 4.0**2 / (2 * 7.5)
    sim_sleep(mock, 15.0)
    s = mock.snapshot()
    assert s["mode"] == "BRAKE" and s["armed"]
    assert math.dist(s["position"], stop) < 0.02
    # Asking LOITER is accepted at once, as ArduCopter does: and with SITL's RC it descends.
    assert c.command(176, CUSTOM, LOITER) == ACCEPTED
    assert vertical_speed_after(mock, 1.8) > 2.3


def test_guided_holds_when_the_companion_stops(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=4.0)
    airborne(mock, c)
    # A moving pos+vel+acc target, then silence: GUID_TIMEOUT zeroes velocity and
    # acceleration; the target (moved on along its velocity until then) is held.
    t0 = mock.snapshot()["t"]
    while (t := mock.snapshot()["t"] - t0) < 3.0:
        c.setpoint(x=1.0 * t, y=0.0, z=-6.0, mask=PVA, vel=(1.0, 0.0, 0.0))
        time.sleep(0.02 / mock.config.speed)
    last_x = 1.0 * (mock.snapshot()["t"] - t0)
    assert wait_for(lambda: any(r["event"] == "guided_timeout" for r in records(mock, "event")), 5)
    sim_sleep(mock, 5.0)
    held = mock.snapshot()["position"]
    sim_sleep(mock, 10.0)
    s = mock.snapshot()
    assert s["mode"] == "GUIDED" and math.dist(s["position"], held) < 0.02
    assert s["position"][2] == pytest.approx(-6.0, abs=0.05)
    assert s["position"][0] == pytest.approx(last_x + 3.0, abs=0.3)  # GUID_TIMEOUT 3 s at 1 m/s


def test_cli_flags_reach_the_config() -> None:
    from sitl_mock.__main__ import build_parser

    args = build_parser().parse_args(["--autopilot", "ardupilot", "--rc-throttle", "none", "--ekf-origin-delay", "5",
                                      "--spool-up", "1.5", "--no-shaping"])
    assert (args.rc_throttle, args.ekf_origin_delay, args.spool_up, args.shaping) == (None, 5.0, 1.5, False)
    args = build_parser().parse_args(["--rc-throttle", "1500"])
    assert (args.rc_throttle, args.ekf_origin_delay, args.spool_up, args.shaping) == (1500, 40.0, 3.0, True)
    with pytest.raises(SystemExit):
        build_parser().parse_args(["--rc-throttle", "mid"])
