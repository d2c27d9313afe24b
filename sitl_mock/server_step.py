"""The mock autopilot's simulation step (`Simulation`): scheduled faults, the time-dependent rules
(failsafes, timeouts, auto-disarm), the target each mode flies to, the vehicle's physics step
and the telemetry due.
"""

from __future__ import annotations

import math
import struct
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from pymavlink.dialects.v20 import common as mav

from .protocol import Behaviour, Flavour, land_speed
from .server_config import FAILSAFE_ACTION
from .server_modes import ModeRules
from .shaping import PX4_LIMIT_PARAMS, px4_vehicle_limits
from .vehicle import Target

if TYPE_CHECKING:
    # the flavour rules (sitl_mock.ardupilot) take the whole autopilot; this class is one layer
    # of it, so `self` is handed over as what it is at run time
    from .server import MockAutopilot


class Simulation(ModeRules):
    """One fixed-rate simulation step and the decisions made in it."""

    # ------------------------------------------------------------------ simulation step

    def _step(self) -> None:
        # t from a step count, not a running sum, so that timings in the log do not drift.
        self._step_count += 1
        self.t = self._step_count * self.dt
        while self._schedule and self._schedule[0][0] <= self.t:
            _, kind, arg = self._schedule.pop(0)
            self._scheduled(kind, arg)
        if self.t < self.rebooting_until:
            self._update_snapshot()
            return
        self._rules()
        if self.px4 is not None:
            self.px4.step()
        target = self._target()
        self.vehicle.step(self.dt, target, self.armed, self.wind)
        self._after_physics()
        self._telemetry(target)
        if self._step_count % self._log_every == 0:
            s = self.vehicle.state
            self.log.write(
                "state", self.t, pos=s.pos.tolist(), vel=s.vel.tolist(), acc=s.acc.tolist(),
                yaw=s.yaw, mode=self.mode, armed=self.armed, landed=self.landed,
            )
        self._update_snapshot()

    def _scheduled(self, kind: str, arg: Any) -> None:
        if kind == "pause":
            self.pause_link(float(arg))
        elif kind == "reboot":
            self.reboot()
        elif kind == "takeover":
            ok, why = self.pilot_set_mode(str(arg))
            if not ok:
                self.log.write("event", self.t, event="takeover_refused", mode=arg, reason=why)

    def _rules(self) -> None:
        """Autopilot-side decisions that depend on time: failsafes, timeouts, auto-disarm."""
        if self.flavour is Flavour.ARDUPILOT:
            self.ap.tick(cast("MockAutopilot", self))  # EKF origin, RC failsafe (sitl_mock.ardupilot)
        if (self.flavour is Flavour.PX4 and self.armed and self.user_mode == "OFFBOARD"
                and self.failsafe_mode is None):
            loss_t = self._param("COM_OF_LOSS_T")
            if self.t - self.last_sp > loss_t:
                self._offboard_failsafe()
        if (
            self.flavour is Flavour.ARDUPILOT
            and self.mode == "GUIDED"
            and self.follow_target is not None
            and self.t - self.last_sp > self._param("GUID_TIMEOUT")
        ):
            ft = self.follow_target
            if np.any(np.isfinite(ft.vel) & (ft.vel != 0)) or np.any(np.isfinite(ft.acc) & (ft.acc != 0)):
                # ArduPilot zeroes the velocity/acceleration feed-forward, keeps the position.
                ft.vel = np.where(np.isfinite(ft.vel), 0.0, ft.vel)
                ft.acc = np.where(np.isfinite(ft.acc), 0.0, ft.acc)
                if not np.any(np.isfinite(ft.pos)):
                    ft.vel = np.zeros(3)
                self.log.write("event", self.t, event="guided_timeout")

    def _offboard_failsafe(self) -> None:
        """PX4's mode fallback for a lost offboard signal (failsafe.cpp checkModeFallback).

        COM_OBL_RC_ACT 0-2 fall back to Position, Altitude or Stabilized mode, which need RC;
        the mock has none, so the fallback chain ends in Return, as PX4's does. OFFBOARD stays
        the user's mode: a setpoint arriving while armed ends the failsafe (`_on_setpoint`).
        """
        action = int(self._param("COM_OBL_RC_ACT"))
        target = {3: "RTL", 4: "LAND", 5: "LOITER", 6: "terminate", 7: "disarm"}.get(action, "RTL")
        self.log.write("event", self.t, event="failsafe", cause="offboard_loss",
                       last_setpoint_t=self.last_sp, action=target)
        args = struct.pack("<IB", self.modes.custom_mode(self.user_mode), FAILSAFE_ACTION[target])
        self._report(mav.MAV_SEVERITY_CRITICAL, "Failsafe activated: no offboard signal",
                     "commander_failsafe_enter_generic", args, internal=mav.MAV_SEVERITY_WARNING)
        if target in ("terminate", "disarm"):
            self._disarm("failsafe")
            return
        self.failsafe_mode = target
        self._set_mode(target, "failsafe")

    def _clear_failsafe(self, reason: str) -> None:
        self.failsafe_mode = None
        self.log.write("event", self.t, event="failsafe_cleared", reason=reason, mode=self.user_mode)
        self._set_mode(self.user_mode, reason)

    def _after_physics(self) -> None:
        s = self.vehicle.state
        if not self.armed:
            self.landed_since = self.t if not self.landed else self.landed_since
            return
        if not self.landed:
            if self.landed_since != math.inf and self.flavour is Flavour.PX4:
                self._report(mav.MAV_SEVERITY_INFO, "Takeoff detected", "commander_takeoff_detected")
            self.airborne_since_arm = True
            self.landed_since = math.inf
            return
        if self.landed_since == math.inf:
            self.landed_since = self.t
            if self.airborne_since_arm:
                self.log.write("event", self.t, event="landed", pos=s.pos.tolist())
                if self.flavour is Flavour.PX4:
                    self._report(mav.MAV_SEVERITY_INFO, "Landing detected", "commander_landing_detected")
        landed_for = self.t - self.landed_since
        behaviour = self.modes.behaviour(self.mode)
        if self.airborne_since_arm:
            if self.flavour is Flavour.PX4:
                limit = self._param("COM_DISARM_LAND")
            else:
                limit = 1.0 if behaviour in (Behaviour.LAND, Behaviour.RTL) else self._param("DISARM_DELAY")
            if limit > 0 and landed_for >= limit:
                self._disarm("auto-disarm after landing")
            return
        if self.flavour is Flavour.ARDUPILOT and self.guided_taken_off:
            return  # takeoff in progress: motors spooling up
        limit = self._param("COM_DISARM_PRFLT") if self.flavour is Flavour.PX4 else self._param("DISARM_DELAY")
        if limit > 0 and self.t - self.arm_t >= limit and landed_for >= limit:
            self._disarm("auto-disarm: no takeoff")

    def _target(self) -> Target | None:
        # --- flavour hooks: ArduPilot's modes and GUIDED shaping (sitl_mock.ardupilot); PX4's
        # MPC_* velocity and tilt limits (sitl_mock.shaping)
        if self.flavour is Flavour.ARDUPILOT:
            return self.ap.target(cast("MockAutopilot", self))
        if self.config.shaping:
            self.vehicle.limits = px4_vehicle_limits({n: float(self.params[n].value) for n in PX4_LIMIT_PARAMS})
        return self._base_target()

    def _base_target(self) -> Target | None:
        if not self.armed:
            return None
        s = self.vehicle.state
        behaviour = self.modes.behaviour(self.mode)
        if behaviour is Behaviour.FOLLOW:
            if self.flavour is Flavour.ARDUPILOT and self.landed and not self.guided_taken_off:
                return Target.hold(np.array([s.pos[0], s.pos[1], self.ground_z]), s.yaw)
            return self.follow_target if self.follow_target is not None else self.hold_target
        if behaviour is Behaviour.TAKEOFF:
            goal = np.array([self.takeoff_xy[0], self.takeoff_xy[1], self.home_ned[2] - self.takeoff_alt])
            if abs(s.pos[2] - goal[2]) < 0.1 and abs(s.vel[2]) < 0.3:
                self._user_mode("LOITER", "takeoff complete")
                return self.hold_target
            return Target.hold(goal, s.yaw)
        if behaviour is Behaviour.LAND:
            return self._land_target()
        if behaviour is Behaviour.RTL:
            home = self.home_ned
            if not self.rtl_landing and float(np.hypot(s.pos[0] - home[0], s.pos[1] - home[1])) < 0.5:
                self.rtl_landing = True
                self.takeoff_xy = home[:2].copy()
                self.hold_target = Target.hold(np.array([home[0], home[1], s.pos[2]]), s.yaw)
            if self.rtl_landing:
                return self._land_target()
            return Target.hold(np.array([home[0], home[1], min(s.pos[2], self.hold_target.pos[2])]), s.yaw)
        return self.hold_target

    def _land_target(self) -> Target:
        xy = self.hold_target.pos[:2]
        pos = np.array([xy[0], xy[1], np.nan])
        vel = np.array([0.0, 0.0, land_speed(self.flavour, self.params)])
        return Target(pos, vel, np.zeros(3), math.nan, math.nan)
