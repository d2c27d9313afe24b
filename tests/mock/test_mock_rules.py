"""Pure rules: mode numbers as mavutil decodes them, setpoint masks and frames, fault parsing."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mav

from sitl_mock.faults import parse_faults
from sitl_mock.protocol import APM_MODES, PX4_MODES, Flavour, ModeTable, decode_setpoint

HERE = (1.0, 2.0, -3.0)
IGN_POS, IGN_VEL, IGN_ACC = 0b111, 0b111 << 3, 0b111 << 6


def sp(mask: int, frame: int = mav.MAV_FRAME_LOCAL_NED, **kw: float) -> SimpleNamespace:
    fields = dict(x=10.0, y=20.0, z=-5.0, vx=1.0, vy=2.0, vz=-0.5, afx=0.1, afy=0.2, afz=-0.3,
                  yaw=0.5, yaw_rate=0.0)
    fields.update(kw)
    return SimpleNamespace(type_mask=mask, coordinate_frame=frame, **fields)


def heartbeat_for(table: ModeTable, name: str, armed: bool) -> object:
    base = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mav.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
    return mav.MAVLink_heartbeat_message(mav.MAV_TYPE_QUADROTOR, table.autopilot, base,
                                         table.custom_mode(name), mav.MAV_STATE_STANDBY, 3)


@pytest.mark.parametrize("flavour", list(Flavour))
def test_every_mode_decodes_by_mavutil_to_its_own_name(flavour: Flavour) -> None:
    table = ModeTable(flavour)
    for name in PX4_MODES if flavour is Flavour.PX4 else APM_MODES:
        hb = heartbeat_for(table, name, armed=True)
        assert mavutil.mode_string_v10(hb) == name
        assert table.from_custom_mode_field(table.custom_mode(name)) == name


def test_px4_custom_mode_layout_matches_px4_custom_mode_h() -> None:
    table = ModeTable(Flavour.PX4)
    assert table.custom_mode("OFFBOARD") == 6 << 16
    assert table.custom_mode("LOITER") == (4 << 16) | (3 << 24)
    assert table.custom_mode("LAND") == (4 << 16) | (6 << 24)
    assert table.from_custom(4, 0) is None  # AUTO without a sub mode is not a mode
    for name, (base, main, sub) in mavutil.px4_map.items():
        if name in PX4_MODES:
            assert PX4_MODES[name] == (main, sub), name
            assert base & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED


def test_ardupilot_mode_numbers_match_mavutil_acm_table() -> None:
    table = ModeTable(Flavour.ARDUPILOT)
    for name in ("STABILIZE", "GUIDED", "LOITER", "RTL", "LAND", "BRAKE"):
        assert mavutil.mode_mapping_acm[table.custom_mode(name)] == name


def test_mode_aliases_and_bad_names() -> None:
    assert ModeTable(Flavour.PX4).canonical("auto.loiter") == "LOITER"
    assert ModeTable(Flavour.ARDUPILOT).canonical("guided") == "GUIDED"
    with pytest.raises(ValueError, match="unknown px4 mode 'GUIDED'"):
        ModeTable(Flavour.PX4).canonical("GUIDED")


@pytest.mark.parametrize(
    ("mask", "has_pos", "has_vel", "has_acc"),
    [
        (IGN_VEL | IGN_ACC, True, False, False),  # P
        (IGN_POS | IGN_ACC, False, True, False),  # V
        (IGN_POS | IGN_VEL, False, False, True),  # A
        (IGN_ACC, True, True, False),  # P+V
        (0, True, True, True),  # P+V+A
    ],
)
def test_px4_accepts_p_v_a_combinations(mask: int, has_pos: bool, has_vel: bool, has_acc: bool) -> None:
    d = decode_setpoint(Flavour.PX4, sp(mask), HERE, 0.0)
    assert d.valid and d.setpoint is not None
    s = d.setpoint
    assert all(math.isfinite(v) == has_pos for v in s.pos)
    assert all(math.isfinite(v) == has_vel for v in s.vel)
    assert all(math.isfinite(v) == has_acc for v in s.acc)


def test_px4_masks_per_axis() -> None:
    d = decode_setpoint(Flavour.PX4, sp(0b110 | IGN_VEL | IGN_ACC), HERE, 0.0)  # x only
    assert d.setpoint is not None
    assert d.setpoint.pos[0] == 10.0 and math.isnan(d.setpoint.pos[1]) and math.isnan(d.setpoint.pos[2])


@pytest.mark.parametrize("frame", [mav.MAV_FRAME_LOCAL_OFFSET_NED, mav.MAV_FRAME_BODY_OFFSET_NED,
                                   mav.MAV_FRAME_GLOBAL, mav.MAV_FRAME_LOCAL_ENU])
def test_px4_ignores_frames_other_than_local_and_body_ned(frame: int) -> None:
    d = decode_setpoint(Flavour.PX4, sp(0, frame), HERE, 0.0)
    assert not d.valid and d.setpoint is None and not d.stop
    assert f"frame {frame}" in d.reason


def test_px4_rejects_force_with_acceleration_but_not_without() -> None:
    assert not decode_setpoint(Flavour.PX4, sp(512), HERE, 0.0).valid
    assert decode_setpoint(Flavour.PX4, sp(512 | IGN_ACC), HERE, 0.0).valid


def test_px4_all_ignored_is_not_a_setpoint() -> None:
    assert not decode_setpoint(Flavour.PX4, sp(IGN_POS | IGN_VEL | IGN_ACC), HERE, 0.0).valid


def test_px4_body_ned_rotates_by_heading_and_offsets_position() -> None:
    d = decode_setpoint(Flavour.PX4, sp(IGN_ACC, mav.MAV_FRAME_BODY_NED, x=1.0, y=0.0, z=0.0,
                                        vx=1.0, vy=0.0, vz=0.0), HERE, math.pi / 2)
    assert d.setpoint is not None
    assert d.setpoint.pos == pytest.approx((1.0, 3.0, -3.0))
    assert d.setpoint.vel == pytest.approx((0.0, 1.0, 0.0))


def test_ardupilot_group_masking_ignores_whole_group() -> None:
    # Only the x-position bit set: ArduPilot drops the whole position group -> velocity control.
    d = decode_setpoint(Flavour.ARDUPILOT, sp(0b001 | IGN_ACC), HERE, 0.0)
    assert d.setpoint is not None
    assert all(math.isnan(v) for v in d.setpoint.pos)
    assert d.setpoint.vel == (1.0, 2.0, -0.5)


@pytest.mark.parametrize("frame", [mav.MAV_FRAME_GLOBAL, mav.MAV_FRAME_LOCAL_ENU, 3])
def test_ardupilot_unsupported_frame_means_stop(frame: int) -> None:
    d = decode_setpoint(Flavour.ARDUPILOT, sp(0, frame), HERE, 0.0)
    assert d.stop and d.setpoint is None


def test_ardupilot_unsupported_combination_means_stop() -> None:
    d = decode_setpoint(Flavour.ARDUPILOT, sp(IGN_VEL), HERE, 0.0)  # position + acceleration
    assert d.stop and d.setpoint is None


def test_ardupilot_offset_and_body_frames() -> None:
    d = decode_setpoint(Flavour.ARDUPILOT, sp(IGN_VEL | IGN_ACC, mav.MAV_FRAME_LOCAL_OFFSET_NED,
                                              x=1.0, y=1.0, z=-1.0), HERE, 0.0)
    assert d.setpoint is not None and d.setpoint.pos == pytest.approx((2.0, 3.0, -4.0))
    d = decode_setpoint(Flavour.ARDUPILOT, sp(IGN_POS | IGN_ACC, mav.MAV_FRAME_BODY_OFFSET_NED,
                                              vx=1.0, vy=0.0, vz=0.0), HERE, math.pi / 2)
    assert d.setpoint is not None and d.setpoint.vel == pytest.approx((0.0, 1.0, 0.0))


def test_ardupilot_force_set_with_acceleration_ignored() -> None:
    d = decode_setpoint(Flavour.ARDUPILOT, sp(512), HERE, 0.0)
    assert not d.valid and d.setpoint is None and not d.stop


def test_parse_faults() -> None:
    spec = parse_faults(["drop=0.1", "latency=50ms", "pause=10:3", "reject-arming", "reboot=4.5"])
    assert spec.drop == 0.1 and spec.latency_s == pytest.approx(0.05)
    assert spec.pauses == [(10.0, 3.0)] and spec.reboots == [4.5] and spec.reject_arming
    with pytest.raises(ValueError, match="drop: fraction"):
        parse_faults(["drop=2"])
    with pytest.raises(ValueError, match="pause: expected AT:SECONDS"):
        parse_faults(["pause=10"])
    with pytest.raises(ValueError, match="unknown fault 'explode'"):
        parse_faults(["explode=1"])
