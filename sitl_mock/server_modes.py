"""The mock autopilot's mode and arming rules per flavour (`ModeRules`): mode changes (the user's,
a failsafe's), arm / disarm with each autopilot's checks, takeoff, link pauses and reboot.
"""

from __future__ import annotations

import math
import struct
from typing import TYPE_CHECKING, cast

import numpy as np
from pymavlink.dialects.v20 import common as mav

from . import events as px4_events
from . import telemetry as tm
from .protocol import Behaviour, Flavour
from .server_config import ARM_REASON, REBOOT_SILENCE_S
from .server_telemetry import TelemetryStreams
from .vehicle import Target

if TYPE_CHECKING:
    # the flavour rules (sitl_mock.ardupilot) take the whole autopilot; this class is one layer
    # of it, so `self` is handed over as what it is at run time
    from .server import MockAutopilot


class ModeRules(TelemetryStreams):
    """Modes and arming, as PX4 and ArduPilot decide them."""

    # ------------------------------------------------------------------ modes, arming

    def _set_mode(self, name: str, reason: str) -> None:
        if name == self.mode:
            return
        old = self.mode
        self.mode = name
        s = self.vehicle.state
        self.hold_target = Target.hold(s.pos.copy(), s.yaw)
        if self.landed:
            self.hold_target.pos[2] = min(s.pos[2], self.ground_z)
        self.rtl_landing = False
        self.ap.on_mode()
        if name == self.modes.follow_mode:
            # PX4 publishes trajectory setpoints only once in OFFBOARD, so it starts from
            # a hold until the next setpoint; GUIDED starts by holding too.
            self.follow_target = None
        if self.modes.behaviour(name) is Behaviour.TAKEOFF:
            self.takeoff_xy = s.pos[:2].copy()
        self.log.write("mode", self.t, **{"from": old, "to": name, "reason": reason})
        self._report(mav.MAV_SEVERITY_INFO, f"Mode {old} -> {name} ({reason})"[:50], None)
        self._send_heartbeat()

    def _user_mode(self, name: str, reason: str) -> None:
        """The user's (or navigator's) mode change: it also ends a failsafe."""
        self.user_mode = name
        if not self.modes.prevents_arming(name) and self.modes.behaviour(name) is not Behaviour.TAKEOFF:
            self.mode_after_disarm = name
        self.failsafe_mode = None
        self._set_mode(name, reason)

    def request_mode(self, name: str, source: str) -> tuple[int, str]:
        """A mode change asked for over MAVLink or by the pilot; returns (MAV_RESULT, why)."""
        if self.flavour is Flavour.PX4 and name == "OFFBOARD" and not self.stream_ok():
            why = "Switching to Offboard denied: no offboard signal"
            args = struct.pack("<IB", self.modes.custom_mode(name), px4_events.NAV_MODE[name])  # navigation_mode_t
            self._report(mav.MAV_SEVERITY_CRITICAL, why, "commander_modeswitch_not_avail", args,
                         internal=mav.MAV_SEVERITY_INFO)
            self._report(mav.MAV_SEVERITY_ERROR, "No offboard signal", "check_modes_offboard_no_signal")
            self.log.write("event", self.t, event="mode_refused", mode=name, source=source, reason=why)
            return int(mav.MAV_RESULT_TEMPORARILY_REJECTED), why
        self._user_mode(name, source)
        return int(mav.MAV_RESULT_ACCEPTED), ""

    def pilot_set_mode(self, mode: str) -> tuple[bool, str]:
        name = self.modes.canonical(mode)
        result, why = self.request_mode(name, "pilot")
        return result == mav.MAV_RESULT_ACCEPTED, why

    def _refuse(self) -> int:
        return int(mav.MAV_RESULT_DENIED if self.flavour is Flavour.PX4 else mav.MAV_RESULT_FAILED)

    def _refuse_arming(self) -> int:
        """PX4 answers a denied arm/disarm transition with TEMPORARILY_REJECTED."""
        return int(mav.MAV_RESULT_TEMPORARILY_REJECTED if self.flavour is Flavour.PX4 else mav.MAV_RESULT_FAILED)

    def arm(self, force: bool) -> tuple[int, str]:
        if self.armed:
            return int(mav.MAV_RESULT_ACCEPTED), ""
        why, event = "", ""
        if self.px4 is not None and not force:
            refusal = self.px4.arm_refusal()  # PX4 has said why in its own events
            if refusal:
                self.log.write("event", self.t, event="arming_refused", reason=refusal)
                return self._refuse_arming(), refusal
        if self.reject_arming:
            why, event = "Arming denied: preflight checks failed", "check_rc_dl_no_dllink"
        elif self.flavour is Flavour.PX4 and self.mode == "OFFBOARD" and not self.stream_ok():
            why, event = "Arming denied: no offboard signal", "check_modes_offboard_no_signal"
        elif self.modes.prevents_arming(self.mode) and not force:
            why, event = f"Arming denied: not armable in {self.mode}", "mock_arm_denied_mode"
        elif self.flavour is Flavour.ARDUPILOT and not force and (
                fails := self.ap.prearm_failures(cast("MockAutopilot", self))):
            for text in fails[1:]:  # ArduPilot reports every failing check
                self._text(mav.MAV_SEVERITY_CRITICAL, text)
            why, event = fails[0], ""
        if why:
            # PX4's arming checks report as errors; the old STATUSTEXT was critical.
            self._report(mav.MAV_SEVERITY_ERROR if self.events else mav.MAV_SEVERITY_CRITICAL, why, event)
            self.log.write("event", self.t, event="arming_refused", reason=why)
            return self._refuse_arming() if self.flavour is Flavour.PX4 else self._refuse(), why
        self.armed = True
        self.arm_t = self.t
        self.airborne_since_arm = False
        self.guided_taken_off = False
        self.landed_since = self.t
        s = self.vehicle.state
        self.hold_target = Target.hold(s.pos.copy(), s.yaw)
        self.log.write("event", self.t, event="armed", mode=self.mode)
        self._report(mav.MAV_SEVERITY_INFO, "Armed", "commander_armed_by", bytes([ARM_REASON["command"]]))
        if self.flavour is Flavour.PX4:
            # PX4 (COM_HOME_EN) sets home where it arms, and streams the new home at once.
            self.home_ned = s.pos.copy()
            self._send(tm.home_position(self.enc.mav, self.origin, self.home_ned, int((self.t - self.boot_t) * 1e6)))
        else:
            self.ap.on_armed(cast("MockAutopilot", self))  # ArduPilot: home where it arms, sent at once
        self._send_heartbeat()
        return int(mav.MAV_RESULT_ACCEPTED), ""

    def _disarm(self, reason: str) -> None:
        self.armed = False
        self.guided_taken_off = False
        self.log.write("event", self.t, event="disarmed", reason=reason)
        self._report(mav.MAV_SEVERITY_INFO, f"Disarmed: {reason}"[:50], "commander_disarmed_by",
                     bytes([ARM_REASON.get(reason, ARM_REASON["command"])]))
        if self.flavour is Flavour.PX4:
            # PX4 ends any failsafe and goes back to the last user mode one can arm in.
            self.failsafe_mode = None
            self.user_mode = self.mode_after_disarm
            self._set_mode(self.user_mode, "disarmed")
        self._update_snapshot()  # so that whoever sees the heartbeat sees its effect too
        self._send_heartbeat()

    def disarm(self, force: bool) -> tuple[int, str]:
        if not self.armed:
            return int(mav.MAV_RESULT_ACCEPTED), ""
        if not self.landed and not force:
            why = "Disarming denied: not landed"
            self._report(mav.MAV_SEVERITY_CRITICAL, why, "commander_disarm_denied_not_landed",
                         internal=mav.MAV_SEVERITY_INFO)
            return self._refuse_arming(), why
        self._disarm("command" if not force else "forced")
        return int(mav.MAV_RESULT_ACCEPTED), ""

    def takeoff(self, param7: float) -> tuple[int, str]:
        s = self.vehicle.state
        if self.flavour is Flavour.PX4:
            # PX4's param7 is an AMSL altitude; NaN means MIS_TAKEOFF_ALT above home.
            home_amsl = self.origin.alt - float(self.home_ned[2])
            alt = param7 - home_amsl if math.isfinite(param7) else self._param("MIS_TAKEOFF_ALT")
            if alt <= 0.0:
                why = "takeoff altitude below home"
                self._report(mav.MAV_SEVERITY_CRITICAL, why, "mock_takeoff_denied_alt")
                return int(mav.MAV_RESULT_DENIED), why
            if not math.isfinite(param7):
                self._report(mav.MAV_SEVERITY_INFO, f"Using default takeoff altitude: {alt:.1f} m",
                             "navigator_takeoff_default_alt", struct.pack("<f", alt))
            self.takeoff_alt = alt
            self._user_mode("TAKEOFF", "takeoff command")
            return int(mav.MAV_RESULT_ACCEPTED), ""
        why = ""
        if self.mode != "GUIDED":
            why = f"Takeoff refused: mode {self.mode} is not GUIDED"
        elif not self.armed:
            why = "Takeoff refused: not armed"
        elif not self.landed or self.guided_taken_off:
            why = "Takeoff refused: already flying"
        elif not (math.isfinite(param7) and param7 > 0):
            why = "Takeoff refused: altitude must be > 0"
        if why:
            self._report(mav.MAV_SEVERITY_WARNING, why, None)
            self.log.write("event", self.t, event="takeoff_refused", reason=why)
            return int(mav.MAV_RESULT_FAILED), why
        self.guided_taken_off = True
        self.takeoff_alt = param7
        self.follow_target = Target.hold(np.array([s.pos[0], s.pos[1], self.home_ned[2] - param7]), s.yaw)
        self.log.write("event", self.t, event="takeoff", alt=param7)
        return int(mav.MAV_RESULT_ACCEPTED), ""

    def pause_link(self, seconds: float) -> None:
        self.link_faults.pause(self.t, seconds)
        self.log.write("event", self.t, event="link_paused", seconds=seconds)

    def reboot(self) -> None:
        self.log.write("event", self.t, event="reboot")
        self.link_faults.clear()
        self._reset_state()
        self.rebooting_until = self.t + REBOOT_SILENCE_S
        self.boot_t = self.rebooting_until  # the clock restarts when it has booted
        for mid in self.next_due:
            self.next_due[mid] = self.rebooting_until
        self.log.write("mode", self.t, **{"from": None, "to": self.mode, "reason": "reboot"})
        self._update_snapshot()
