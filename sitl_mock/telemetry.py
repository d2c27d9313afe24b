"""Builders for the messages the mock streams or answers on request."""

from __future__ import annotations

import math
import struct
import time
from dataclasses import dataclass
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mav

from . import events, mavwire
from .protocol import Flavour, Param

EARTH_RADIUS = 6378137.0

SENSORS = (
    mav.MAV_SYS_STATUS_SENSOR_3D_GYRO
    | mav.MAV_SYS_STATUS_SENSOR_3D_ACCEL
    | mav.MAV_SYS_STATUS_SENSOR_3D_MAG
    | mav.MAV_SYS_STATUS_SENSOR_ABSOLUTE_PRESSURE
    | mav.MAV_SYS_STATUS_SENSOR_GPS
    | mav.MAV_SYS_STATUS_SENSOR_ANGULAR_RATE_CONTROL
    | mav.MAV_SYS_STATUS_SENSOR_ATTITUDE_STABILIZATION
    | mav.MAV_SYS_STATUS_SENSOR_YAW_POSITION
    | mav.MAV_SYS_STATUS_SENSOR_Z_ALTITUDE_CONTROL
    | mav.MAV_SYS_STATUS_SENSOR_XY_POSITION_CONTROL
    | mav.MAV_SYS_STATUS_SENSOR_MOTOR_OUTPUTS
    | mav.MAV_SYS_STATUS_AHRS
)


@dataclass(frozen=True)
class Home:
    """A geodetic point, used for the local origin (the estimator's, GPS_GLOBAL_ORIGIN)."""

    lat: float
    lon: float
    alt: float  # m AMSL

    def to_global(self, ned: np.ndarray) -> tuple[int, int, int]:
        """(lat 1e7 deg, lon 1e7 deg, alt mm AMSL) of a local NED point (flat earth)."""
        lat = self.lat + math.degrees(ned[0] / EARTH_RADIUS)
        lon = self.lon + math.degrees(ned[1] / (EARTH_RADIUS * math.cos(math.radians(self.lat))))
        return round(lat * 1e7), round(lon * 1e7), round((self.alt - ned[2]) * 1000)


def heartbeat(m: mav.MAVLink, autopilot: int, base_flags: int, armed: bool, custom_mode: int) -> Any:
    base = base_flags | mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
    if armed:
        base |= mav.MAV_MODE_FLAG_SAFETY_ARMED
    status = mav.MAV_STATE_ACTIVE if armed else mav.MAV_STATE_STANDBY
    return m.heartbeat_encode(mav.MAV_TYPE_QUADROTOR, autopilot, base, custom_mode, status)


def sys_status(m: mav.MAVLink, armable: bool) -> Any:
    health = SENSORS | (mav.MAV_SYS_STATUS_PREARM_CHECK if armable else 0)
    present = SENSORS | mav.MAV_SYS_STATUS_PREARM_CHECK
    return m.sys_status_encode(present, present, health, 200, 16000, -1, 90, 0, 0, 0, 0, 0, 0)


def autopilot_version(m: mav.MAVLink, flavour: Flavour, sysid: int) -> Any:
    caps = (
        mav.MAV_PROTOCOL_CAPABILITY_MAVLINK2
        | mav.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_LOCAL_NED
        | mav.MAV_PROTOCOL_CAPABILITY_SET_POSITION_TARGET_GLOBAL_INT
        | mav.MAV_PROTOCOL_CAPABILITY_SET_ATTITUDE_TARGET
        | mav.MAV_PROTOCOL_CAPABILITY_COMMAND_INT
        | mav.MAV_PROTOCOL_CAPABILITY_MISSION_INT
        | mav.MAV_PROTOCOL_CAPABILITY_PARAM_FLOAT
    )
    if flavour is Flavour.PX4:
        caps |= mav.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE
        version = (1 << 24) | (14 << 16) | (0 << 8) | 255  # 1.14.0 official
    else:
        caps |= mav.MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_C_CAST
        version = (4 << 24) | (5 << 16) | (0 << 8) | 255  # Copter 4.5.0 official
    return m.autopilot_version_encode(
        caps, version, 0, 0, 0, [0] * 8, [0] * 8, [0] * 8, 0, 0, 0x4D4F434B00 + sysid, [0] * 18
    )


def home_position(m: mav.MAVLink, origin: Home, home_ned: np.ndarray, t_usec: int) -> Any:
    """HOME_POSITION: the home point both geodetic and in the local frame of `origin`."""
    lat, lon, alt = origin.to_global(home_ned)
    x, y, z = (float(v) for v in home_ned)
    return m.home_position_encode(lat, lon, alt, x, y, z, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, t_usec)


def gps_global_origin(m: mav.MAVLink, origin: Home, t_usec: int) -> Any:
    lat, lon, alt = origin.to_global(np.zeros(3))
    return m.gps_global_origin_encode(lat, lon, alt, t_usec)


def global_position(m: mav.MAVLink, origin: Home, home_z: float, ms: int, pos: np.ndarray, vel: np.ndarray,
                    yaw: float) -> Any:
    """GLOBAL_POSITION_INT: alt AMSL from the origin, relative_alt above home."""
    lat, lon, alt = origin.to_global(pos)
    hdg = round(math.degrees(yaw) % 360.0 * 100) % 36000
    return m.global_position_int_encode(
        ms, lat, lon, alt, round((home_z - pos[2]) * 1000),
        round(vel[0] * 100), round(vel[1] * 100), round(vel[2] * 100), hdg,
    )


def gps_raw(m: mav.MAVLink, home: Home, t_usec: int, pos: np.ndarray, vel: np.ndarray) -> Any:
    lat, lon, alt = home.to_global(pos)
    speed = float(np.hypot(vel[0], vel[1]))
    cog = round(math.degrees(math.atan2(vel[1], vel[0])) % 360.0 * 100) % 36000
    return m.gps_raw_int_encode(t_usec, mav.GPS_FIX_TYPE_3D_FIX, lat, lon, alt, 80, 120,
                                round(speed * 100), cog, 12)


def position_target(m: mav.MAVLink, ms: int, pos: np.ndarray, vel: np.ndarray, acc: np.ndarray,
                    yaw: float, yaw_rate: float) -> Any:
    mask = 0
    bits = ((pos, (1, 2, 4)), (vel, (8, 16, 32)), (acc, (64, 128, 256)))
    for values, axis_bits in bits:
        for v, b in zip(values, axis_bits, strict=True):
            if not math.isfinite(v):
                mask |= b
    if not math.isfinite(yaw):
        mask |= 1024
    if not math.isfinite(yaw_rate):
        mask |= 2048

    def f(v: float) -> float:
        return float(v) if math.isfinite(v) else 0.0

    return m.position_target_local_ned_encode(
        ms, mav.MAV_FRAME_LOCAL_NED, mask, f(pos[0]), f(pos[1]), f(pos[2]), f(vel[0]), f(vel[1]),
        f(vel[2]), f(acc[0]), f(acc[1]), f(acc[2]), f(yaw), f(yaw_rate),
    )


def system_time(m: mav.MAVLink, ms: int) -> Any:
    return m.system_time_encode(int(time.time() * 1e6), ms)


def encode_param_value(flavour: Flavour, p: Param) -> float:
    """PX4 sends integers bytewise in the float field; ArduPilot casts them."""
    if p.ptype == mav.MAV_PARAM_TYPE_INT32 and flavour is Flavour.PX4:
        return float(struct.unpack("<f", struct.pack("<i", int(p.value)))[0])
    return float(p.value)


def decode_param_value(flavour: Flavour, ptype: int, value: float) -> float:
    if ptype == mav.MAV_PARAM_TYPE_INT32 and flavour is Flavour.PX4:
        return float(struct.unpack("<i", struct.pack("<f", value))[0])
    if ptype == mav.MAV_PARAM_TYPE_INT32:
        return float(round(value))
    return float(value)


def param_value(m: mav.MAVLink, flavour: Flavour, p: Param, count: int, index: int) -> Any:
    return m.param_value_encode(p.name.encode(), encode_param_value(flavour, p), p.ptype, count, index)


def statustext(m: mav.MAVLink, severity: int, text: str) -> Any:
    return m.statustext_encode(severity, text.encode()[:50])


def event(m: mav.MAVLink, name: str, level: int, sequence: int, ms: int, args: bytes = b"",
          internal: int | None = None) -> Any:
    """EVENT (410) with PX4's id for `name` (sitl_mock.events)."""
    return mavwire.event(events.IDS[name], events.log_levels(level, internal), sequence, ms, args)
