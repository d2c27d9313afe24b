"""How the autopilots shape a target with their own kinematic limits before they fly it.

ArduCopter: ``AC_PosControl`` keeps a kinematic path (position, velocity, acceleration
target) and moves it towards each input with jerk-limited square-root shaping
(``libraries/AP_Math/control.cpp``: ``shape_pos_vel_accel[_xy]``, ``shape_vel_accel[_xy]``,
``shape_accel[_xy]``, ``sqrt_controller``, ``update_pos_vel_accel[_xy]``;
``libraries/AC_AttitudeControl/AC_PosControl.cpp``: ``input_pos_vel_accel_xy``,
``input_pos_vel_accel_z``, ``input_vel_accel_xy``, ``input_vel_accel_z``). GUIDED sets its
limits from WPNAV_* (``ArduCopter/mode_guided.cpp`` ``pva_control_start``) and calls the
inputs with ``limit_output = false``: the limits bind the correction, not the feed-forward,
so a plan beyond them lags, then overshoots. The position controller's own P/PID loops are
the mock's vehicle model (``vehicle.py``), which flies the shaped path.

PX4: offboard trajectory setpoints reach ``PositionControl`` unshaped; it constrains the
velocity setpoint (position P + feed-forward) to MPC_XY_VEL_MAX on the horizontal norm and
MPC_Z_VEL_MAX_UP / _DN vertically (``_positionControl``) and the thrust tilt to
MPC_TILTMAX_AIR (``_accelerationControl``, ``ControlMath::limitTilt``). MPC_ACC_* and
MPC_JERK_MAX shape PX4's own flight tasks (position mode, missions), not offboard setpoints.

Pure functions and one small state holder; no sockets, no clock. NED throughout; ArduPilot's
vertical maths (NEU, up positive) is done on ``-z``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from .vehicle import Limits

CORNER_ACCELERATION_RATIO = 1.0 / math.sqrt(2.0)
OVERSPEED_GAIN_Z = 2.0  # AC_PosControl POSCONTROL_OVERSPEED_GAIN_Z
ACCEL_Z_DOWN_CAP = 7.5  # m/s^2: input_*_z constrain(accel_max_z, 0, 750 cm/s^2) for the downward limit


# ----------------------------------------------------------------------------- AP_Math/control.cpp


def sqrt_controller(error: float, p: float, second_ord_lim: float, dt: float) -> float:
    """Linear near zero, sqrt(2 a |e|) far away; never overshoots the error within one step."""
    if second_ord_lim <= 0.0:
        rate = error * p
    elif p == 0.0:
        rate = math.copysign(math.sqrt(2.0 * second_ord_lim * abs(error)), error) if error else 0.0
    else:
        linear_dist = second_ord_lim / (p * p)
        if error > linear_dist:
            rate = math.sqrt(2.0 * second_ord_lim * (error - linear_dist / 2.0))
        elif error < -linear_dist:
            rate = -math.sqrt(2.0 * second_ord_lim * (-error - linear_dist / 2.0))
        else:
            rate = error * p
    if dt > 0.0:
        lim = abs(error) / dt
        return min(max(rate, -lim), lim)
    return rate


Vec2 = tuple[float, float]


def _len(v: Vec2) -> float:
    return math.hypot(v[0], v[1])


def sqrt_controller_xy(error: Vec2, p: float, second_ord_lim: float, dt: float) -> Vec2:
    n = _len(error)
    if n <= 0.0:
        return (0.0, 0.0)
    k = sqrt_controller(n, p, second_ord_lim, dt) / n
    return (error[0] * k, error[1] * k)


def limit_length(v: Vec2, limit: float) -> Vec2:
    n = _len(v)
    if limit > 0.0 and n > limit:
        return (v[0] * limit / n, v[1] * limit / n)
    return v


def limit_accel_corner_xy(vel: Vec2, accel: Vec2, accel_max: float) -> Vec2:
    """Keep cross-track authority in turns: cross-track first (to a_max/sqrt 2), along-track the rest."""
    if accel_max <= 0.0:
        return accel
    vn = _len(vel)
    if vn <= 0.0:
        return limit_length(accel, accel_max)
    ux, uy = vel[0] / vn, vel[1] / vn
    a_dir = ux * accel[0] + uy * accel[1]
    cross = (accel[0] - ux * a_dir, accel[1] - uy * a_dir)
    if a_dir * a_dir <= cross[0] ** 2 + cross[1] ** 2:
        return limit_length(accel, accel_max)
    cross = limit_length(cross, CORNER_ACCELERATION_RATIO * accel_max)
    max_dir = math.sqrt(max(0.0, accel_max * accel_max - cross[0] ** 2 - cross[1] ** 2))
    a_dir = min(max(a_dir, -max_dir), max_dir)
    return (cross[0] + ux * a_dir, cross[1] + uy * a_dir)


def shape_accel(accel_desired: float, accel: float, jerk_max: float, dt: float) -> float:
    step = jerk_max * dt
    return accel + min(max(accel_desired - accel, -step), step)


def shape_accel_xy(accel_desired: Vec2, accel: Vec2, jerk_max: float, dt: float) -> Vec2:
    d = limit_length((accel_desired[0] - accel[0], accel_desired[1] - accel[1]), jerk_max * dt)
    return (accel[0] + d[0], accel[1] + d[1])


def shape_vel_accel(vel_desired: float, accel_desired: float, vel: float, accel: float, accel_min: float,
                    accel_max: float, jerk_max: float, dt: float, limit_total: bool) -> float:
    vel_error = vel_desired - vel
    kpa = jerk_max / accel_max if vel_error > 0.0 else jerk_max / -accel_min
    target = min(max(sqrt_controller(vel_error, kpa, jerk_max, dt), accel_min), accel_max)
    target += accel_desired
    if limit_total:
        target = min(max(target, accel_min), accel_max)
    return shape_accel(target, accel, jerk_max, dt)


def shape_vel_accel_xy(vel_desired: Vec2, accel_desired: Vec2, vel: Vec2, accel: Vec2,
                       accel_max: float, jerk_max: float, dt: float, limit_total: bool) -> Vec2:
    target = sqrt_controller_xy((vel_desired[0] - vel[0], vel_desired[1] - vel[1]), jerk_max / accel_max, jerk_max,
                                dt)
    target = limit_accel_corner_xy(vel_desired, target, accel_max)
    target = (target[0] + accel_desired[0], target[1] + accel_desired[1])
    if limit_total:
        target = limit_length(target, accel_max)
    return shape_accel_xy(target, accel, jerk_max, dt)


def shape_pos_vel_accel(pos_desired: float, vel_desired: float, accel_desired: float, pos: float, vel: float,
                        accel: float, vel_min: float, vel_max: float, accel_min: float, accel_max: float,
                        jerk_max: float, dt: float, limit_total: bool) -> float:
    pos_error = pos_desired - pos
    if pos_error > 0.0:
        tc_max, kpv = -0.5 * accel_min, 0.5 * jerk_max / -accel_min
    else:
        tc_max, kpv = 0.5 * accel_max, 0.5 * jerk_max / accel_max
    vel_target = sqrt_controller(pos_error, kpv, tc_max, dt)
    if vel_min < 0.0 or vel_max > 0.0:
        vel_target = min(max(vel_target, vel_min), vel_max)
    vel_target += vel_desired
    if limit_total and vel_max > vel_min:
        vel_target = min(max(vel_target, vel_min), vel_max)
    return shape_vel_accel(vel_target, accel_desired, vel, accel, accel_min, accel_max, jerk_max, dt, limit_total)


def shape_pos_vel_accel_xy(pos_desired: Vec2, vel_desired: Vec2, accel_desired: Vec2, pos: Vec2, vel: Vec2,
                           accel: Vec2, vel_max: float, accel_max: float, jerk_max: float, dt: float,
                           limit_total: bool) -> Vec2:
    vel_target = sqrt_controller_xy((pos_desired[0] - pos[0], pos_desired[1] - pos[1]), 0.5 * jerk_max / accel_max,
                                    0.5 * accel_max, dt)
    if vel_max > 0.0:
        vel_target = limit_length(vel_target, vel_max)
    vel_target = (vel_target[0] + vel_desired[0], vel_target[1] + vel_desired[1])
    if limit_total and vel_max > 0.0:
        vel_target = limit_length(vel_target, vel_max)
    return shape_vel_accel_xy(vel_target, accel_desired, vel, accel, accel_max, jerk_max, dt, limit_total)


Vec3 = list[float]


def project(pos: Vec3, vel: Vec3, accel: Vec3, dt: float) -> tuple[Vec3, Vec3]:
    """update_pos_vel_accel with no limit: move a target forward by dt along its own motion."""
    h = 0.5 * dt * dt
    return ([p + v * dt + a * h for p, v, a in zip(pos, vel, accel, strict=True)],
            [v + a * dt for v, a in zip(vel, accel, strict=True)])


# ----------------------------------------------------------------------------- ArduCopter


@dataclass(frozen=True)
class ApLimits:
    """One mode's AC_PosControl limits, SI units (the parameters are in cm)."""

    speed_xy: float
    accel_xy: float
    jerk_xy: float
    speed_up: float
    speed_down: float
    accel_z: float
    jerk_z: float


def guided_limits(params: dict[str, float]) -> ApLimits:
    """GUIDED (pva_control_start): WPNAV_SPEED / WPNAV_ACCEL / WPNAV_SPEED_UP / _DN / WPNAV_ACCEL_Z,
    jerk PSC_JERK_XY / PSC_JERK_Z (AC_PosControl set_max_speed_accel_xy/_z)."""
    return ApLimits(
        speed_xy=params["WPNAV_SPEED"] / 100.0, accel_xy=params["WPNAV_ACCEL"] / 100.0,
        jerk_xy=params["PSC_JERK_XY"], speed_up=params["WPNAV_SPEED_UP"] / 100.0,
        speed_down=abs(params["WPNAV_SPEED_DN"]) / 100.0, accel_z=params["WPNAV_ACCEL_Z"] / 100.0,
        jerk_z=params["PSC_JERK_Z"],
    )


class ApPath:
    """AC_PosControl's kinematic path (_pos_target, _vel_desired, _accel_desired) in NED.

    Each ``input_*`` call advances the path by dt and returns the input moved forward along
    its own velocity and acceleration, as AC_PosControl writes back into GUIDED's target
    (so a GUIDED target with a velocity keeps moving between messages). Plain floats: this
    runs every simulation step, in the companion's process in the in-process tests.
    """

    def __init__(self, pos: Sequence[float], vel: Sequence[float], acc: Sequence[float] | None = None) -> None:
        self.pos: Vec3 = [float(v) for v in pos]
        self.vel: Vec3 = [float(v) for v in vel]
        self.acc: Vec3 = [0.0, 0.0, 0.0] if acc is None else [float(v) for v in acc]

    def _overspeed(self, lim: ApLimits) -> float:
        up = -self.vel[2]  # ArduPilot's vertical maths is up-positive
        if lim.speed_down > 0.0 and up < -lim.speed_down:
            return OVERSPEED_GAIN_Z * up / -lim.speed_down
        if lim.speed_up > 0.0 and up > lim.speed_up:
            return OVERSPEED_GAIN_Z * up / lim.speed_up
        return 1.0

    def _advance(self, dt: float) -> None:
        self.pos, self.vel = project(self.pos, self.vel, self.acc, dt)

    def input_pos_vel_accel(self, pos: Vec3, vel: Vec3, acc: Vec3, lim: ApLimits, dt: float,
                            limit_total: bool) -> tuple[Vec3, Vec3]:
        gain = self._overspeed(lim)
        self._advance(dt)
        ax, ay = shape_pos_vel_accel_xy((pos[0], pos[1]), (vel[0], vel[1]), (acc[0], acc[1]),
                                        (self.pos[0], self.pos[1]), (self.vel[0], self.vel[1]),
                                        (self.acc[0], self.acc[1]), lim.speed_xy, lim.accel_xy, lim.jerk_xy, dt,
                                        limit_total)
        a_z = lim.accel_z * gain
        up_acc = shape_pos_vel_accel(-pos[2], -vel[2], -acc[2], -self.pos[2], -self.vel[2], -self.acc[2],
                                     -lim.speed_down, lim.speed_up, -min(max(a_z, 0.0), ACCEL_Z_DOWN_CAP), a_z,
                                     lim.jerk_z * gain, dt, limit_total)
        self.acc = [ax, ay, -up_acc]
        return project(pos, vel, acc, dt)

    def input_vel_accel(self, vel: Vec3, acc: Vec3, lim: ApLimits, dt: float, limit_total: bool) -> Vec3:
        gain = self._overspeed(lim)
        self._advance(dt)
        ax, ay = shape_vel_accel_xy((vel[0], vel[1]), (acc[0], acc[1]), (self.vel[0], self.vel[1]),
                                    (self.acc[0], self.acc[1]), lim.accel_xy, lim.jerk_xy, dt, limit_total)
        a_z = lim.accel_z * gain
        up_acc = shape_vel_accel(-vel[2], -acc[2], -self.vel[2], -self.acc[2],
                                 -min(max(a_z, 0.0), ACCEL_Z_DOWN_CAP), a_z, lim.jerk_z * gain, dt, limit_total)
        self.acc = [ax, ay, -up_acc]
        return [v + a * dt for v, a in zip(vel, acc, strict=True)]

    def input_accel(self, acc: Vec3, lim: ApLimits, dt: float) -> None:
        """Acceleration-only targets: jerk-limited (AC_PosControl input_accel_xy / _z)."""
        self._advance(dt)
        ax, ay = shape_accel_xy((acc[0], acc[1]), (self.acc[0], self.acc[1]), lim.jerk_xy, dt)
        self.acc = [ax, ay, shape_accel(acc[2], self.acc[2], lim.jerk_z, dt)]


# ----------------------------------------------------------------------------- PX4


@dataclass(frozen=True)
class Px4Limits:
    """PositionControl's constraints on an offboard setpoint (velocity setpoint and tilt)."""

    speed_xy: float
    speed_up: float
    speed_down: float
    tilt_deg: float


PX4_LIMIT_PARAMS = ("MPC_XY_VEL_MAX", "MPC_Z_VEL_MAX_UP", "MPC_Z_VEL_MAX_DN", "MPC_TILTMAX_AIR")


def px4_limits(params: dict[str, float]) -> Px4Limits:
    return Px4Limits(params["MPC_XY_VEL_MAX"], params["MPC_Z_VEL_MAX_UP"], params["MPC_Z_VEL_MAX_DN"],
                     params["MPC_TILTMAX_AIR"])


def px4_vehicle_limits(params: dict[str, float]) -> Limits:
    lim = px4_limits(params)
    return Limits(lim.speed_xy, lim.speed_up, lim.speed_down, lim.tilt_deg)
