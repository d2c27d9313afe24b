"""The mock autopilot's outgoing telemetry (`TelemetryStreams`): HEARTBEAT and the streamed
messages at their intervals (set by SET_MESSAGE_INTERVAL or ArduPilot's stream groups).
"""

from __future__ import annotations

import math

import numpy as np
from pymavlink.dialects.v20 import common as mav

from . import telemetry as tm
from .protocol import Behaviour, Flavour
from .server_state import AutopilotState
from .vehicle import Target


class TelemetryStreams(AutopilotState):
    """Telemetry: what is sent, when (`_telemetry` each simulation step) and how."""

    # ------------------------------------------------------------------ outgoing telemetry

    def _send_heartbeat(self) -> None:
        base = 0
        if self.flavour is Flavour.PX4:
            main = (self.modes.custom_mode(self.mode) >> 16) & 0xFF
            base = 29 if main in (4, 6) else 81
        else:
            base = 16 | (8 if self.modes.behaviour(self.mode) is not Behaviour.HOLD else 64)
        self._send(tm.heartbeat(self.enc.mav, self.modes.autopilot, base, self.armed,
                                self.modes.custom_mode(self.mode)))

    def _telemetry(self, target: Target | None) -> None:
        for mid, due in self.next_due.items():
            if self.t + 1e-9 >= due:
                interval = self.intervals[mid]
                if math.isinf(interval):
                    continue
                self.next_due[mid] = max(due + interval, self.t)
                self._send_stream(mid, target)

    def _noisy(self) -> tuple[np.ndarray, np.ndarray]:
        s = self.vehicle.state
        if self.config.noise <= 0:
            return s.pos, s.vel
        n = self.config.noise
        return s.pos + self.rng.normal(0, n, 3), s.vel + self.rng.normal(0, n / 2, 3)

    def _landed_state(self) -> int:
        if self.landed:
            return int(mav.MAV_LANDED_STATE_ON_GROUND)
        if self.modes.behaviour(self.mode) is Behaviour.LAND:
            return int(mav.MAV_LANDED_STATE_LANDING)
        if self.modes.behaviour(self.mode) is Behaviour.TAKEOFF:
            return int(mav.MAV_LANDED_STATE_TAKEOFF)
        return int(mav.MAV_LANDED_STATE_IN_AIR)

    def _send_stream(self, mid: int, target: Target | None, requested: bool = False) -> None:
        """One message now: due on its stream, or `requested` (REQUEST_MESSAGE; an event that
        sends it at once), which PX4 answers for messages its streams send only on change."""
        m = self.enc.mav
        ms = self.time_boot_ms
        t_usec = int((self.t - self.boot_t) * 1e6)
        s = self.vehicle.state
        if self.flavour is Flavour.ARDUPILOT and not self.ap.sends(mid):
            return  # no EKF origin yet (sitl_mock.ardupilot)
        if self.px4 is not None and not self.px4.sends(mid, requested):
            return  # no estimate or global origin yet, or not new (sitl_mock.px4)
        if mid == mav.MAVLINK_MSG_ID_HEARTBEAT:
            self._send_heartbeat()
        elif mid == mav.MAVLINK_MSG_ID_SYS_STATUS:
            self._send(tm.sys_status(m, armable=not self.reject_arming))
        elif mid == mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            pos, vel = self._noisy()
            if self.px4 is not None:
                pos, vel = self.px4.estimate(pos, vel)
            self._send(m.local_position_ned_encode(ms, *pos.tolist(), *vel.tolist()))
        elif mid == mav.MAVLINK_MSG_ID_ATTITUDE:
            roll, pitch, yaw = self.vehicle.attitude()
            self._send(m.attitude_encode(ms, roll, pitch, yaw, 0.0, 0.0, s.yaw_rate))
        elif mid == mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            pos, vel = self._noisy()
            self._send(tm.global_position(m, self.origin, float(self.home_ned[2]), ms, pos, vel, s.yaw))
        elif mid == mav.MAVLINK_MSG_ID_GPS_RAW_INT:
            pos, vel = self._noisy()
            self._send(tm.gps_raw(m, self.origin, t_usec, pos, vel))
        elif mid == mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            self._send(m.extended_sys_state_encode(mav.MAV_VTOL_STATE_UNDEFINED, self._landed_state()))
        elif mid == mav.MAVLINK_MSG_ID_HOME_POSITION:
            self._send(tm.home_position(m, self.origin, self.home_ned, t_usec))
        elif mid == mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
            self._send(tm.gps_global_origin(m, self.origin, t_usec))
        elif mid == mav.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED:
            if target is not None:
                self._send(tm.position_target(m, ms, target.pos, target.vel, target.acc, target.yaw,
                                              target.yaw_rate))
        elif mid == mav.MAVLINK_MSG_ID_SYSTEM_TIME:
            self._send(tm.system_time(m, ms))
