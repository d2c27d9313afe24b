"""Per-autopilot rules: mode numbers, command semantics, setpoint masks and frames.

Everything here is pure (no sockets, no clock) so that the rules can be read and tested
apart from the transport. The rules follow PX4's ``mavlink_receiver.cpp``
(handle_message_set_position_target_local_ned) and ArduPilot Copter's
``GCS_Mavlink.cpp`` (handle_message_set_position_target_local_ned).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum
from typing import Any

from pymavlink.dialects.v20 import common as mav

FORCE_SET_MAGIC = 21196

# Bits of SET_POSITION_TARGET_LOCAL_NED.type_mask.
POS_BITS = (1, 2, 4)
VEL_BITS = (8, 16, 32)
ACC_BITS = (64, 128, 256)
FORCE_SET = 512
YAW_IGNORE = 1024
YAW_RATE_IGNORE = 2048


class Flavour(StrEnum):
    PX4 = "px4"
    ARDUPILOT = "ardupilot"


class Behaviour(StrEnum):
    """What the vehicle does in a mode, independent of its name."""

    FOLLOW = "follow"  # OFFBOARD / GUIDED: track external setpoints
    HOLD = "hold"  # hold position (loiter, position mode with centred sticks)
    TAKEOFF = "takeoff"
    LAND = "land"
    RTL = "rtl"
    BRAKE = "brake"


# PX4: name -> (main, sub). Names are those mavutil.interpret_px4_mode prints.
PX4_MODES: dict[str, tuple[int, int]] = {
    "MANUAL": (1, 0),
    "ALTCTL": (2, 0),
    "POSCTL": (3, 0),
    "TAKEOFF": (4, 2),
    "LOITER": (4, 3),
    "MISSION": (4, 4),
    "RTL": (4, 5),
    "LAND": (4, 6),
    "ACRO": (5, 0),
    "OFFBOARD": (6, 0),
    "STABILIZED": (7, 0),
}
PX4_BEHAVIOUR: dict[str, Behaviour] = {
    "MANUAL": Behaviour.HOLD,
    "ALTCTL": Behaviour.HOLD,
    "POSCTL": Behaviour.HOLD,
    "TAKEOFF": Behaviour.TAKEOFF,
    "LOITER": Behaviour.HOLD,
    "MISSION": Behaviour.HOLD,
    "RTL": Behaviour.RTL,
    "LAND": Behaviour.LAND,
    "ACRO": Behaviour.HOLD,
    "OFFBOARD": Behaviour.FOLLOW,
    "STABILIZED": Behaviour.HOLD,
}
# Names as written in PX4's own UI / docs, accepted on the control socket.
PX4_ALIASES = {
    "AUTO.LOITER": "LOITER",
    "HOLD": "LOITER",
    "AUTO.LAND": "LAND",
    "AUTO.TAKEOFF": "TAKEOFF",
    "AUTO.RTL": "RTL",
    "AUTO.MISSION": "MISSION",
    "POSITION": "POSCTL",
    "ALTITUDE": "ALTCTL",
}

# ArduPilot Copter mode numbers (mavutil.mode_mapping_acm).
APM_MODES: dict[str, int] = {
    "STABILIZE": 0,
    "ACRO": 1,
    "ALT_HOLD": 2,
    "AUTO": 3,
    "GUIDED": 4,
    "LOITER": 5,
    "RTL": 6,
    "CIRCLE": 7,
    "LAND": 9,
    "POSHOLD": 16,
    "BRAKE": 17,
    "SMART_RTL": 21,
}
APM_BEHAVIOUR: dict[str, Behaviour] = {
    "STABILIZE": Behaviour.HOLD,
    "ACRO": Behaviour.HOLD,
    "ALT_HOLD": Behaviour.HOLD,
    "AUTO": Behaviour.HOLD,
    "GUIDED": Behaviour.FOLLOW,
    "LOITER": Behaviour.HOLD,
    "RTL": Behaviour.RTL,
    "CIRCLE": Behaviour.HOLD,
    "LAND": Behaviour.LAND,
    "POSHOLD": Behaviour.HOLD,
    "BRAKE": Behaviour.BRAKE,
    "SMART_RTL": Behaviour.RTL,
}
APM_ALIASES = {"HOLD": "LOITER", "POSCTL": "LOITER", "POSITION": "LOITER"}


@dataclass(frozen=True)
class ModeTable:
    flavour: Flavour

    @property
    def autopilot(self) -> int:
        if self.flavour is Flavour.PX4:
            return int(mav.MAV_AUTOPILOT_PX4)
        return int(mav.MAV_AUTOPILOT_ARDUPILOTMEGA)

    @property
    def boot_mode(self) -> str:
        # PX4 >= 1.14 starts with AUTO.LOITER as the user's intended mode (UserModeIntention).
        return "LOITER" if self.flavour is Flavour.PX4 else "STABILIZE"

    def prevents_arming(self, name: str) -> bool:
        """Modes one cannot arm in (PX4's mode_req_prevent_arming; ArduPilot: LAND, RTL)."""
        return self.behaviour(name) in (Behaviour.LAND, Behaviour.RTL)

    @property
    def follow_mode(self) -> str:
        return "OFFBOARD" if self.flavour is Flavour.PX4 else "GUIDED"

    @property
    def hold_mode(self) -> str:
        return "LOITER"

    def canonical(self, name: str) -> str:
        """Canonical mode name, or ValueError naming the flavour's valid modes."""
        up = name.strip().upper()
        modes: dict[str, Any] = PX4_MODES if self.flavour is Flavour.PX4 else APM_MODES
        aliases = PX4_ALIASES if self.flavour is Flavour.PX4 else APM_ALIASES
        up = aliases.get(up, up)
        if up not in modes:
            raise ValueError(
                f"mode: unknown {self.flavour.value} mode {name!r}; valid: {sorted(modes)}"
            )
        return up

    def behaviour(self, name: str) -> Behaviour:
        table = PX4_BEHAVIOUR if self.flavour is Flavour.PX4 else APM_BEHAVIOUR
        return table[name]

    def custom_mode(self, name: str) -> int:
        if self.flavour is Flavour.PX4:
            main, sub = PX4_MODES[name]
            return (main << 16) | (sub << 24)
        return APM_MODES[name]

    def from_custom(self, main_or_mode: int, sub: int = 0) -> str | None:
        """Mode name from DO_SET_MODE parameters (PX4: main, sub; ArduPilot: mode number)."""
        if self.flavour is Flavour.PX4:
            for name, (m, s) in PX4_MODES.items():
                # PX4 treats AUTO with sub 0 as unspecified: refuse it rather than guess.
                if m == main_or_mode and (s == sub or (m != 4 and sub == 0)):
                    return name
            return None
        for name, num in APM_MODES.items():
            if num == main_or_mode:
                return name
        return None

    def from_custom_mode_field(self, custom_mode: int) -> str | None:
        """Mode name from a SET_MODE message's 32-bit custom_mode."""
        if self.flavour is Flavour.PX4:
            return self.from_custom((custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF)
        return self.from_custom(custom_mode)


@dataclass(frozen=True)
class Setpoint:
    """A decoded target in local NED, per axis; NaN where the axis is not commanded.

    ``pos`` is already absolute (offsets and body rotation applied).
    """

    pos: tuple[float, float, float]
    vel: tuple[float, float, float]
    acc: tuple[float, float, float]
    yaw: float
    yaw_rate: float


@dataclass(frozen=True)
class SetpointDecision:
    """Outcome of one SET_POSITION_TARGET_LOCAL_NED under a flavour's rules.

    valid: counts as a proof-of-life setpoint (PX4 stream check).
    setpoint: what to track if the vehicle is in its follow mode (None: nothing to apply).
    stop: ArduPilot's "input is not valid so stop" (hold at the current position).
    reason: why it was ignored/rejected, empty when accepted.
    """

    valid: bool
    setpoint: Setpoint | None
    stop: bool
    reason: str


NAN3 = (math.nan, math.nan, math.nan)


def _rot(yaw: float, v: tuple[float, float, float]) -> tuple[float, float, float]:
    c, s = math.cos(yaw), math.sin(yaw)
    return (c * v[0] - s * v[1], s * v[0] + c * v[1], v[2])


def _masked(values: tuple[float, float, float], mask: int, bits: tuple[int, ...]) -> tuple[float, float, float]:
    return tuple(math.nan if mask & b else float(v) for v, b in zip(values, bits, strict=True))  # type: ignore[return-value]


def target_matches(target_system: int, target_component: int, sysid: int, compid: int) -> bool:
    return target_system in (0, sysid) and target_component in (0, compid)


def decode_setpoint(
    flavour: Flavour,
    msg: Any,
    position: tuple[float, float, float],
    yaw_now: float,
) -> SetpointDecision:
    """Apply the flavour's rules for frames and masks to a SET_POSITION_TARGET_LOCAL_NED."""
    if flavour is Flavour.PX4:
        return _decode_px4(msg, position, yaw_now)
    return _decode_apm(msg, position, yaw_now)


def _yaw_fields(msg: Any, mask: int) -> tuple[float, float]:
    yaw = math.nan if mask & YAW_IGNORE else float(msg.yaw)
    rate = math.nan if mask & YAW_RATE_IGNORE else float(msg.yaw_rate)
    return yaw, rate


def _decode_px4(msg: Any, position: tuple[float, float, float], yaw_now: float) -> SetpointDecision:
    mask = int(msg.type_mask)
    frame = int(msg.coordinate_frame)
    pos = _masked((msg.x, msg.y, msg.z), mask, POS_BITS)
    vel = _masked((msg.vx, msg.vy, msg.vz), mask, VEL_BITS)
    acc = _masked((msg.afx, msg.afy, msg.afz), mask, ACC_BITS)
    if frame == mav.MAV_FRAME_BODY_NED:
        # PX4 rotates body-frame targets by the current heading; positions are offsets
        # from the current position.
        pos = tuple(p + q for p, q in zip(_rot(yaw_now, pos), position, strict=True))  # type: ignore[assignment]
        vel = _rot(yaw_now, vel)
        acc = _rot(yaw_now, acc)
    elif frame != mav.MAV_FRAME_LOCAL_NED:
        return SetpointDecision(False, None, False, f"coordinate frame {frame} unsupported")
    has_acc = any(math.isfinite(a) for a in acc)
    if has_acc and mask & FORCE_SET:
        return SetpointDecision(False, None, False, "force setpoint not supported")
    if not (any(math.isfinite(v) for v in pos + vel) or has_acc):
        return SetpointDecision(False, None, False, "all of position, velocity, acceleration ignored")
    yaw, rate = _yaw_fields(msg, mask)
    return SetpointDecision(True, Setpoint(pos, vel, acc, yaw, rate), False, "")


def _decode_apm(msg: Any, position: tuple[float, float, float], yaw_now: float) -> SetpointDecision:
    mask = int(msg.type_mask)
    frame = int(msg.coordinate_frame)
    if frame not in (
        mav.MAV_FRAME_LOCAL_NED,
        mav.MAV_FRAME_LOCAL_OFFSET_NED,
        mav.MAV_FRAME_BODY_NED,
        mav.MAV_FRAME_BODY_OFFSET_NED,
    ):
        return SetpointDecision(True, None, True, f"coordinate frame {frame} unsupported: stop")
    # ArduPilot ignores a whole group if any of its bits is set.
    pos_ignore = any(mask & b for b in POS_BITS)
    vel_ignore = any(mask & b for b in VEL_BITS)
    acc_ignore = any(mask & b for b in ACC_BITS)
    if mask & FORCE_SET and not acc_ignore:
        return SetpointDecision(False, None, False, "force setpoint not supported")
    body = frame in (mav.MAV_FRAME_BODY_NED, mav.MAV_FRAME_BODY_OFFSET_NED)
    offset = frame != mav.MAV_FRAME_LOCAL_NED
    pos, vel, acc = NAN3, NAN3, NAN3
    if not pos_ignore:
        pos = (float(msg.x), float(msg.y), float(msg.z))
        if body:
            pos = _rot(yaw_now, pos)
        if offset:
            pos = (pos[0] + position[0], pos[1] + position[1], pos[2] + position[2])
    if not vel_ignore:
        vel = (float(msg.vx), float(msg.vy), float(msg.vz))
        vel = _rot(yaw_now, vel) if body else vel
    if not acc_ignore:
        acc = (float(msg.afx), float(msg.afy), float(msg.afz))
        acc = _rot(yaw_now, acc) if body else acc
    yaw, rate = _yaw_fields(msg, mask)
    zero = (0.0, 0.0, 0.0)
    if not pos_ignore and not vel_ignore:
        sp = Setpoint(pos, vel, acc if not acc_ignore else zero, yaw, rate)
    elif pos_ignore and not vel_ignore:
        sp = Setpoint(NAN3, vel, acc if not acc_ignore else zero, yaw, rate)
    elif pos_ignore and vel_ignore and not acc_ignore:
        sp = Setpoint(NAN3, NAN3, acc, yaw, rate)
    elif not pos_ignore and vel_ignore and acc_ignore:
        sp = Setpoint(pos, zero, zero, yaw, rate)
    else:
        return SetpointDecision(True, None, True, f"unsupported type_mask {mask:#06x}: stop")
    return SetpointDecision(True, sp, False, "")


@dataclass(frozen=True)
class Param:
    name: str
    value: float
    ptype: int  # MAV_PARAM_TYPE


def default_params(flavour: Flavour) -> dict[str, Param]:
    i32, f32 = int(mav.MAV_PARAM_TYPE_INT32), int(mav.MAV_PARAM_TYPE_REAL32)
    if flavour is Flavour.PX4:
        items = [
            Param("COM_OF_LOSS_T", 1.0, f32),
            # 0 position, 1 altitude, 2 stabilized, 3 return, 4 land, 5 hold, 6 terminate,
            # 7 disarm. PX4's default 0; without RC (the mock has none) 0-2 cannot run and
            # PX4's mode fallback ends in Return.
            Param("COM_OBL_RC_ACT", 0, i32),
            Param("COM_DISARM_PRFLT", 10.0, f32),
            Param("COM_DISARM_LAND", 2.0, f32),
            Param("MIS_TAKEOFF_ALT", 2.5, f32),
            Param("MPC_LAND_SPEED", 0.7, f32),
            # Limits of multicopter position control, PX4's defaults (mc_pos_control_params.c):
            # velocity and tilt bind offboard setpoints (sitl_mock.shaping); acceleration and
            # jerk shape PX4's own flight tasks and are served for companions to read.
            Param("MPC_XY_VEL_MAX", 12.0, f32),
            Param("MPC_Z_VEL_MAX_UP", 3.0, f32),
            Param("MPC_Z_VEL_MAX_DN", 1.5, f32),
            Param("MPC_ACC_HOR_MAX", 5.0, f32),
            Param("MPC_ACC_UP_MAX", 4.0, f32),
            Param("MPC_ACC_DOWN_MAX", 3.0, f32),
            Param("MPC_TILTMAX_AIR", 45.0, f32),
            Param("MPC_JERK_MAX", 8.0, f32),
        ]
    else:
        items = [
            Param("GUID_TIMEOUT", 3.0, f32),
            Param("DISARM_DELAY", 10, i32),
            Param("LAND_SPEED", 50, i32),
            Param("PILOT_TKOFF_ALT", 0.0, f32),
            # GUIDED's shaping limits (AC_WPNav.h defaults, cm/s and cm/s^2; PSC_JERK_* m/s^3,
            # AC_PosControl.cpp), read live by sitl_mock.shaping.
            Param("WPNAV_SPEED", 1000.0, f32),
            Param("WPNAV_ACCEL", 250.0, f32),
            Param("WPNAV_SPEED_UP", 250.0, f32),
            Param("WPNAV_SPEED_DN", 150.0, f32),
            Param("WPNAV_ACCEL_Z", 100.0, f32),
            Param("PSC_JERK_XY", 5.0, f32),
            Param("PSC_JERK_Z", 5.0, f32),
            # Pilot modes (sitl_mock.ardupilot): Parameters.cpp / AC_Loiter defaults.
            Param("PILOT_SPEED_UP", 250, i32),
            Param("PILOT_SPEED_DN", 0, i32),  # 0: PILOT_SPEED_UP
            Param("PILOT_ACCEL_Z", 250, i32),
            Param("THR_DZ", 100, i32),
            Param("LOIT_SPEED", 1250.0, f32),
            Param("LOIT_BRK_ACCEL", 250.0, f32),
            Param("LOIT_BRK_JERK", 500.0, f32),
            # RC failsafe: 1 RTL, FS_THR_VALUE pwm, RC_FS_TIMEOUT s; FS_OPTIONS 16 (bit 2, value 4,
            # would continue GUIDED on RC loss: not set by default).
            Param("FS_THR_ENABLE", 1, i32),
            Param("FS_THR_VALUE", 975, i32),
            Param("RC_FS_TIMEOUT", 1.0, f32),
            Param("FS_OPTIONS", 16, i32),
            # Stream-group rates (Hz) at boot on the first MAVLink link, as ArduCopter 4.7 names
            # them (SR0_*/SR1_* before): 0 in a stock set, so nothing but HEARTBEAT and
            # STATUSTEXT goes out until a client asks (REQUEST_DATA_STREAM, SET_MESSAGE_INTERVAL).
            Param("MAV1_EXT_STAT", 0, i32),
            Param("MAV1_POSITION", 0, i32),
            Param("MAV1_EXTRA1", 0, i32),
            Param("MAV1_EXTRA3", 0, i32),
        ]
    return {p.name: p for p in items}


def land_speed(flavour: Flavour, params: dict[str, Param]) -> float:
    if flavour is Flavour.PX4:
        return float(params["MPC_LAND_SPEED"].value)
    return float(params["LAND_SPEED"].value) / 100.0
