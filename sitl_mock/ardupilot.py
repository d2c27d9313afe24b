"""ArduCopter's rules where a stock SITL is stricter than a kind mock (issues 20 and 26).

- Pilot modes fly the RC input: SITL with no transmitter sends throttle 1000 (below the
  deadband), so LOITER / ALT_HOLD / POSHOLD descend at PILOT_SPEED_DN (0: PILOT_SPEED_UP,
  2.5 m/s) and STABILIZE / ACRO fall (motors at ground idle); mid-stick, or no RC ever seen,
  holds (``ArduCopter/Attitude.cpp`` get_pilot_desired_climb_rate, ``mode_loiter.cpp``,
  ``mode_stabilize.cpp``; ``libraries/AP_RCProtocol/AP_RCProtocol_UDP.cpp``).
- RC failsafe (``ArduCopter/radio.cpp`` read_radio / set_throttle_and_failsafe,
  ``events.cpp`` failsafe_radio_on_event, should_disarm_on_failsafe): RC lost for
  RC_FS_TIMEOUT while armed or once seen, or throttle below FS_THR_VALUE, runs FS_THR_ENABLE's
  action; GUIDED continues only with FS_OPTIONS bit 2.
- No position estimate until the EKF origin is set: no LOCAL_POSITION_NED, GPS_GLOBAL_ORIGIN
  or HOME_POSITION (``GCS_Common.cpp`` send_local_position / send_gps_global_origin /
  send_home_position return when the origin or home is unset); and LOCAL_POSITION_NED only
  ``position_after_origin_s`` after the origin (measured on stock SITL: home and origin ~22 s
  before the first one; ``send_local_position`` also needs the EKF's position), and arming in a mode that
  requires a position refused with "PreArm: Need Position Estimate"
  (``ArduCopter/AP_Arming.cpp`` mandatory_gps_checks).
- Home is set where the vehicle arms and sent at once (AP_Arming_Copter::arm,
  ``AP_AHRS::set_home`` sends HOME and ORIGIN); the estimate on the ground has moved
  ``home_shift_at_arming`` from the origin's home by then (measured: home moved ~1 cm at arming).
- Motors spool for ``spool_up_s`` after arming before any climb (measured 3.0 s).
- BRAKE stops with 7.5 m/s^2 and holds where it stopped, climb rate 0, until the mode changes
  (``ArduCopter/mode_brake.cpp``: BRAKE_MODE_DECEL_RATE 750, BRAKE_MODE_SPEED_Z 250, no
  timeout unless another mode sets one).
- GUIDED targets shaped with WPNAV_* (``sitl_mock.shaping``).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from pymavlink.dialects.v20 import common as mav

from . import telemetry as tm
from .shaping import ApLimits, ApPath, guided_limits
from .vehicle import G, Limits, Target

if TYPE_CHECKING:
    from .server import MockAutopilot

# Mode::requires_GPS() is true for these (mode.h and each mode's header).
REQUIRES_POSITION = frozenset({"GUIDED", "LOITER", "AUTO", "RTL", "CIRCLE", "POSHOLD", "BRAKE", "SMART_RTL"})
CLIMB_RATE_MODES = frozenset({"LOITER", "ALT_HOLD", "POSHOLD"})  # pilot's throttle = climb rate
HOLDS_XY = frozenset({"LOITER", "POSHOLD"})  # centred sticks: brake, then hold the position
MANUAL_THROTTLE = frozenset({"STABILIZE", "ACRO"})  # pilot's throttle = thrust
BRAKE_DECEL = 7.5  # m/s^2, BRAKE_MODE_DECEL_RATE
BRAKE_SPEED_Z = 2.5  # m/s, BRAKE_MODE_SPEED_Z
RC_MIN, RC_MAX = 1100, 1900  # RC3_MIN / RC3_MAX defaults: pwm -> throttle control 0..1000
# FS_THR_ENABLE -> the failsafe's mode (events.cpp failsafe_radio_on_event; 2 continues only AUTO).
FS_THR_ACTION = {1: "RTL", 2: "RTL", 3: "LAND", 4: "SMART_RTL", 5: "SMART_RTL", 6: "RTL", 7: "BRAKE"}
FS_OPTION_RC_CONTINUE_IF_GUIDED = 4
NEED_POSITION = "PreArm: Need Position Estimate"
THROTTLE_BELOW_FAILSAFE = "PreArm: Throttle below Failsafe"
NAN3 = np.full(3, math.nan)


def throttle_control(pwm: int | None) -> float:
    """channel_throttle->get_control_in(): 0..1000 from the pwm (no RC: 0)."""
    if pwm is None:
        return 0.0
    return min(max((pwm - RC_MIN) * 1000.0 / (RC_MAX - RC_MIN), 0.0), 1000.0)


def pilot_climb_rate(pwm: int | None, seen: bool, failsafe: bool, params: dict[str, float]) -> float:
    """Copter::get_pilot_desired_climb_rate, m/s up: 0 in failsafe or with no RC ever seen."""
    if failsafe or not seen:
        return 0.0
    thr = throttle_control(pwm)
    dz = min(max(params["THR_DZ"], 0.0), 400.0)
    top, bottom = 500.0 + dz, 500.0 - dz
    up = params["PILOT_SPEED_UP"]
    down = abs(params["PILOT_SPEED_DN"]) or abs(up)
    if thr < bottom:
        return down * (thr - bottom) / bottom / 100.0
    if thr > top:
        return up * (thr - top) / (1000.0 - top) / 100.0
    return 0.0


def pilot_limits(params: dict[str, float]) -> ApLimits:
    """LOITER / POSHOLD / ALT_HOLD: AC_Loiter braking and PILOT_* vertical (mode_loiter.cpp init)."""
    down = abs(params["PILOT_SPEED_DN"]) or abs(params["PILOT_SPEED_UP"])
    return ApLimits(
        speed_xy=params["LOIT_SPEED"] / 100.0, accel_xy=params["LOIT_BRK_ACCEL"] / 100.0,
        jerk_xy=params["LOIT_BRK_JERK"] / 100.0, speed_up=params["PILOT_SPEED_UP"] / 100.0,
        speed_down=down / 100.0, accel_z=params["PILOT_ACCEL_Z"] / 100.0, jerk_z=params["PSC_JERK_Z"],
    )


def brake_limits(params: dict[str, float]) -> ApLimits:
    return ApLimits(speed_xy=0.0, accel_xy=BRAKE_DECEL, jerk_xy=params["PSC_JERK_XY"], speed_up=BRAKE_SPEED_Z,
                    speed_down=BRAKE_SPEED_Z, accel_z=BRAKE_DECEL, jerk_z=params["PSC_JERK_Z"])


class ArduPilotRules:
    """The ArduPilot flavour's state beyond the common mock: RC, EKF origin, the shaped path."""

    def __init__(self, rc_throttle: int | None, ekf_origin_delay_s: float, spool_up_s: float,
                 shaping: bool, position_after_origin_s: float = 0.0,
                 home_shift_at_arming: tuple[float, float] = (0.0, 0.0)) -> None:
        self.rc_throttle = rc_throttle  # pwm the autopilot receives now; None: no RC frames
        self.rc_seen = rc_throttle is not None
        self.ekf_origin_delay_s = ekf_origin_delay_s
        self.position_after_origin_s = position_after_origin_s
        self.home_shift_at_arming = np.asarray(home_shift_at_arming, dtype=float)
        self.spool_up_s = spool_up_s
        self.shaping = shaping
        self.rc_last = 0.0
        self.reset()

    def reset(self) -> None:
        """Boot (and reboot): no origin, no failsafe, no path."""
        self.origin_set = False
        self.origin_t = math.inf  # mock time the origin was set
        self.position_known = False  # LOCAL_POSITION_NED is sent (position_after_origin_s after the origin)
        self.radio_failsafe = False
        self.path: ApPath | None = None
        self._cached: tuple[float, Target | None] | None = None
        self._params: tuple[float, dict[str, float]] | None = None

    # ------------------------------------------------------------------ state per step

    def params(self, mock: MockAutopilot) -> dict[str, float]:
        """The live parameter values, read once per simulated step (PARAM_SET applies at once)."""
        if self._params is None or self._params[0] != mock.t:
            self._params = (mock.t, {name: float(p.value) for name, p in mock.params.items()})
        return self._params[1]

    def tick(self, mock: MockAutopilot) -> None:
        """Called every simulation step: EKF origin, RC frames, RC failsafe."""
        if self.origin_set and not self.position_known and mock.t - self.origin_t >= self.position_after_origin_s:
            self.position_known = True
            mock.log.write("event", mock.t, event="position_estimate", since_origin=mock.t - self.origin_t)
        if not self.origin_set and mock.t - mock.boot_t >= self.ekf_origin_delay_s:
            self.origin_set = True
            self.origin_t = mock.t
            self.position_known = self.position_after_origin_s <= 0.0
            # Copter sets home from the EKF once it has an origin (update_home_from_EKF)
            mock.home_ned = mock.vehicle.state.pos.copy()
            # and the estimate on the ground moves on before arming sets home again (measured
            # ~1 cm); the mock's vehicle is its estimate, so it is moved
            mock.vehicle.state.pos[:2] += self.home_shift_at_arming
            mock.log.write("event", mock.t, event="ekf_origin_set", since_boot=mock.t - mock.boot_t)
            mock._text(mav.MAV_SEVERITY_INFO, "EKF3 IMU0 origin set")
            # AP_AHRS::set_home: "send new home and ekf origin to GCS" (MSG_HOME, MSG_ORIGIN)
            mock._send_stream(mav.MAVLINK_MSG_ID_HOME_POSITION, None)
            mock._send_stream(mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, None)
        p = self.params(mock)
        enabled = int(p["FS_THR_ENABLE"]) != 0
        if self.rc_throttle is not None:
            self.rc_last = mock.t
            self.rc_seen = True
            if self.radio_failsafe and self.rc_throttle >= p["FS_THR_VALUE"]:
                self.radio_failsafe = False
                mock.log.write("event", mock.t, event="radio_failsafe_cleared")
                mock._text(mav.MAV_SEVERITY_WARNING, "Radio Failsafe Cleared")
            elif (enabled and not self.radio_failsafe and mock.armed
                  and self.rc_throttle < p["FS_THR_VALUE"]):
                self._radio_failsafe(mock, p, "throttle below FS_THR_VALUE")
            return
        if (enabled and not self.radio_failsafe and (self.rc_seen or mock.armed)
                and mock.t - self.rc_last >= p["RC_FS_TIMEOUT"]):
            self._radio_failsafe(mock, p, "no RC input")

    def _radio_failsafe(self, mock: MockAutopilot, p: dict[str, float], cause: str) -> None:
        self.radio_failsafe = True
        action = FS_THR_ACTION.get(int(p["FS_THR_ENABLE"]), "LAND")
        landed = mock.landed
        if mock.mode in MANUAL_THROTTLE:
            disarm = landed or throttle_control(self.rc_throttle) <= 0.0
        else:
            disarm = landed
        mock.log.write("event", mock.t, event="failsafe", cause="radio", reason=cause,
                       action="disarm" if disarm else action)
        if not mock.armed:
            return
        if disarm:
            mock._text(mav.MAV_SEVERITY_WARNING, "Radio Failsafe - Disarming")
            mock._disarm("failsafe")
            return
        if mock.mode == "GUIDED" and int(p["FS_OPTIONS"]) & FS_OPTION_RC_CONTINUE_IF_GUIDED:
            mock._text(mav.MAV_SEVERITY_WARNING, "Radio Failsafe - Continuing Guided Mode")
            return
        mock._text(mav.MAV_SEVERITY_WARNING, "Radio Failsafe")
        mock._set_mode(action, "failsafe")

    def set_rc(self, mock: MockAutopilot, pwm: int | None) -> None:
        self.rc_throttle = pwm
        mock.log.write("event", mock.t, event="rc", throttle=pwm)

    # ------------------------------------------------------------------ telemetry, arming, home

    def sends(self, msg_id: int) -> bool:
        """Messages ArduPilot leaves out while it has no EKF origin (and so no home), and
        LOCAL_POSITION_NED until its position estimate follows the origin."""
        if msg_id == mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            return self.position_known
        if self.origin_set:
            return True
        return msg_id not in (mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED, mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN,
                              mav.MAVLINK_MSG_ID_HOME_POSITION)

    def prearm_failures(self, mock: MockAutopilot) -> list[str]:
        p = self.params(mock)
        fails = []
        if int(p["FS_THR_ENABLE"]) != 0 and (self.rc_throttle or 0) < p["FS_THR_VALUE"]:
            fails.append(THROTTLE_BELOW_FAILSAFE)  # pilot_throttle_checks: radio_in 0 with no RC
        if mock.mode in REQUIRES_POSITION and not self.origin_set:
            fails.append(NEED_POSITION)
        return fails

    def on_armed(self, mock: MockAutopilot) -> None:
        """AP_Arming_Copter::arm: home to the current location, HOME_POSITION sent at once."""
        mock.home_ned = mock.vehicle.state.pos.copy()
        mock.log.write("event", mock.t, event="home_set", home=mock.home_ned.tolist(), reason="armed")
        mock._send(tm.home_position(mock.enc.mav, mock.origin, mock.home_ned, int((mock.t - mock.boot_t) * 1e6)))
        mock._send(tm.gps_global_origin(mock.enc.mav, mock.origin, int((mock.t - mock.boot_t) * 1e6)))  # set_home
        self.path = None

    def on_mode(self) -> None:
        """Every mode initialises its controllers from the vehicle's state."""
        self.path = None

    def stop_target(self, mock: MockAutopilot) -> Target:
        """A target GUIDED cannot fly stops it: ModeGuided::init -> velaccel_control_start, zero
        velocity and acceleration, controllers initialised from the vehicle's state; it holds
        where the shaped deceleration ends (GCS_Mavlink.cpp "input is not valid so stop")."""
        self.path = None
        return Target(NAN3.copy(), np.zeros(3), np.zeros(3), mock.vehicle.state.yaw, math.nan)

    # ------------------------------------------------------------------ targets

    def target(self, mock: MockAutopilot) -> Target | None:
        """The target for this step (advances the shaped path once per simulated step)."""
        if self._cached is not None and self._cached[0] == mock.t:
            return self._cached[1]
        tgt = self._target(mock)
        self._cached = (mock.t, tgt)
        return tgt

    def _path(self, mock: MockAutopilot) -> ApPath:
        if self.path is None:
            s = mock.vehicle.state
            self.path = ApPath(s.pos.tolist(), s.vel.tolist(), s.acc.tolist())
        return self.path

    def _ground(self, mock: MockAutopilot) -> Target:
        s = mock.vehicle.state
        self.path = None
        return Target.hold(np.array([s.pos[0], s.pos[1], mock.ground_z]), s.yaw)

    def _target(self, mock: MockAutopilot) -> Target | None:
        mock.vehicle.limits = None
        if not mock.armed:
            self.path = None
            return None
        s = mock.vehicle.state
        if mock.landed and mock.t - mock.arm_t < self.spool_up_s:
            return self._ground(mock)  # motors spooling: no climb yet
        mode = mock.mode
        p = self.params(mock)
        if mode == "GUIDED":
            if mock.landed and not mock.guided_taken_off:
                return self._ground(mock)
            if not self.shaping:
                return mock.follow_target if mock.follow_target is not None else mock.hold_target
            return self._guided(mock, p)
        if mode == "BRAKE":
            if mock.landed:
                return self._ground(mock)
            path = self._path(mock)
            path.input_vel_accel([0.0, 0.0, 0.0], [0.0, 0.0, 0.0], brake_limits(p), mock.dt, limit_total=True)
            return self._flown(mock, path.pos, path.vel, path.acc, s.yaw)
        if mode in CLIMB_RATE_MODES:
            climb = pilot_climb_rate(self.rc_throttle, self.rc_seen, self.radio_failsafe, p)
            if mock.landed and climb <= 0.0:
                self.path = None
                return None  # landed with the throttle low: motors at ground idle
            path = self._path(mock)
            # Sticks centred: zero horizontal velocity (brake, then hold); the climb rate as
            # set_pos_target_z_from_climb_rate_cm shapes it.
            path.input_vel_accel([0.0, 0.0, -climb], [0.0, 0.0, 0.0], pilot_limits(p), mock.dt, limit_total=True)
            if mode in HOLDS_XY:
                return self._flown(mock, path.pos, path.vel, path.acc, s.yaw)
            return self._flown(mock, [math.nan, math.nan, path.pos[2]], [math.nan, math.nan, path.vel[2]],
                               [0.0, 0.0, path.acc[2]], s.yaw)
        if mode in MANUAL_THROTTLE:
            self.path = None
            thr = throttle_control(self.rc_throttle)
            if thr <= 0.0:
                return None  # throttle zero: ground idle, the vehicle falls
            # Mid-stick is about hover thrust (MOT_THST_HOVER); sticks centred: level.
            up = G * (min(thr / 500.0, 2.0) - 1.0)
            return Target(NAN3.copy(), NAN3.copy(), np.array([0.0, 0.0, -up]), s.yaw, math.nan)
        self.path = None
        return mock._base_target()

    def _flown(self, mock: MockAutopilot, pos: list[float], vel: list[float], acc: list[float],
               yaw: float) -> Target:
        # AC_PosControl limits the path, not the total velocity: the response's own
        # velocity clamps would be a second, wrong limit (tilt stays).
        mock.vehicle.limits = Limits(math.inf, math.inf, math.inf, mock.vehicle.params.max_tilt_deg)
        return Target(np.array(pos), np.array(vel), np.array(acc), yaw, math.nan)

    def _guided(self, mock: MockAutopilot, p: dict[str, float]) -> Target:
        ft = mock.follow_target if mock.follow_target is not None else mock.hold_target
        lim = guided_limits(p)
        path = self._path(mock)
        pos, vel, acc = ft.pos.tolist(), ft.vel.tolist(), ft.acc.tolist()
        has_pos = all(math.isfinite(v) for v in pos)
        has_vel = all(math.isfinite(v) for v in vel)
        acc = [a if math.isfinite(a) else 0.0 for a in acc]
        if has_pos:
            # posvelaccel_control_run: limit_output false; the target moves on along its
            # velocity between messages (AC_PosControl writes it back).
            new_pos, new_vel = path.input_pos_vel_accel(pos, vel if has_vel else [0.0, 0.0, 0.0], acc, lim, mock.dt,
                                                        limit_total=False)
            ft.pos = np.array(new_pos)
            if has_vel:
                ft.vel = np.array(new_vel)
        elif has_vel:
            ft.vel = np.array(path.input_vel_accel(vel, acc, lim, mock.dt, limit_total=False))
        else:
            path.input_accel(acc, lim, mock.dt)
        yaw = ft.yaw if math.isfinite(ft.yaw) else math.nan
        tgt = self._flown(mock, path.pos, path.vel, path.acc, yaw)
        tgt.yaw_rate = ft.yaw_rate
        return tgt

