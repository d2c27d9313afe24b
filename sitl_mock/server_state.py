"""The state shared by the parts of the mock autopilot (`AutopilotState`, the base of
`sitl_mock.server.MockAutopilot`): its flight state, snapshot and sending.
"""

from __future__ import annotations

import math
import threading
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mav

from . import events as px4_events
from . import px4
from . import telemetry as tm
from .ardupilot import ArduPilotRules
from .control import ControlServer
from .faults import LinkFaults
from .log import FlightLog
from .protocol import Flavour, ModeTable, Param
from .server_config import APM_GROUPS, DEFAULT_RATES, STREAM_GAP_S, MockConfig
from .transport import Encoder, Link
from .vehicle import Target, Vehicle


class AutopilotState:
    """The state every part of `MockAutopilot` works on, and what they all use: the flight state
    reset at boot and on reboot, the snapshot other threads read, and sending (STATUSTEXT,
    EVENT, any message through the link faults).

    The attributes below are set by `MockAutopilot.__init__` (sitl_mock.server); they are
    declared here so that each part type-checks on its own.
    """

    config: MockConfig
    flavour: Flavour
    modes: ModeTable
    dt: float
    ground_z: float
    origin: tm.Home
    events: bool
    event_seq: int
    params: dict[str, Param]
    vehicle: Vehicle
    enc: Encoder
    log: FlightLog
    link_faults: LinkFaults
    reject_arming: bool
    rng: np.random.Generator
    wind: np.ndarray
    links: list[Link]
    control: ControlServer | None
    _lock: threading.Lock
    _schedule: list[tuple[float, str, Any]]
    t: float
    _step_count: int
    _log_every: int
    _snapshot: dict[str, Any]
    _last_reject_text: dict[str, float]
    _reboot_pending: bool
    ap: ArduPilotRules
    px4: px4.Px4Rules | None

    # ------------------------------------------------------------------ state

    def _reset_state(self) -> None:
        self.boot_t = self.t
        self.mode = self.modes.boot_mode  # the mode in force (PX4's nav_state), as reported
        # PX4's UserModeIntention: the mode the user asked for (a failsafe overrides it while
        # active) and the one to go back to on disarm (never one that prevents arming).
        self.user_mode = self.mode
        self.mode_after_disarm = self.mode
        self.failsafe_mode: str | None = None
        self.armed = False
        self.vehicle.reset()
        # Home: the boot point on the ground; PX4 moves it to where it arms.
        self.home_ned = np.array([0.0, 0.0, self.ground_z])
        self.hold_target = Target.hold(self.home_ned, 0.0)
        self.follow_target: Target | None = None
        self.sp_times: list[float] = []
        self.stream_start = -math.inf
        self.last_sp = -math.inf
        self.arm_t = -math.inf
        self.airborne_since_arm = False
        self.landed_since = self.t
        self.guided_taken_off = False
        self.takeoff_alt = float(self.params["MIS_TAKEOFF_ALT"].value) if self.flavour is Flavour.PX4 else 0.0
        self.takeoff_xy = np.zeros(2)
        self.rtl_landing = False
        self.rebooting_until = -math.inf
        self.ap.reset()
        self.next_due = {mid: self.t for mid in DEFAULT_RATES}
        if self.px4 is not None:
            self.px4.reset()
        self.intervals = {mid: 1.0 / hz for mid, hz in DEFAULT_RATES.items()}
        if self.flavour is Flavour.ARDUPILOT:
            # Stock ArduPilot on a fresh link: HEARTBEAT only (and STATUSTEXT as it happens),
            # plus the groups whose MAV1_* rate parameter is set.
            for mid in self.intervals:
                if mid != mav.MAVLINK_MSG_ID_HEARTBEAT:
                    self.intervals[mid] = math.inf
            for group in APM_GROUPS:
                self._set_group(group, self._param(APM_GROUPS[group][0]))
        self._update_snapshot()

    def _param(self, name: str) -> float:
        return float(self.params[name].value)

    @property
    def time_boot_ms(self) -> int:
        return int((self.t - self.boot_t) * 1000) & 0xFFFFFFFF

    @property
    def landed(self) -> bool:
        return self.vehicle.state.on_ground

    def stream_ok(self) -> bool:
        """PX4 proof of life: valid setpoints at >= 2 Hz for at least the warm-up time.

        PX4's docs ask for a stream older than one second; its code (offboardCheck.cpp)
        only asks for one setpoint within COM_OF_LOSS_T, which ``offboard_warmup_s = 0``
        reproduces.
        """
        warmup = self.config.offboard_warmup_s
        if warmup <= 0:
            return self.t - self.last_sp <= self._param("COM_OF_LOSS_T")
        return self.t - self.last_sp <= STREAM_GAP_S and self.t - self.stream_start >= warmup

    def _update_snapshot(self) -> None:
        s = self.vehicle.state
        with self._lock:
            self._snapshot = {
                "t": self.t,
                "position": s.pos.tolist(),
                "velocity": s.vel.tolist(),
                "yaw": s.yaw,
                "mode": self.mode,
                "armed": self.armed,
                "landed": self.landed,
                "link_paused": self.link_faults.paused(self.t),
                "rebooting": self.t < self.rebooting_until,
                "user_mode": self.user_mode,
                "failsafe": self.failsafe_mode is not None,
                "ground_z": self.ground_z,
                "home": self.home_ned.tolist(),
                "ekf_origin": self.flavour is Flavour.PX4 or self.ap.origin_set,
                "rc_failsafe": self.ap.radio_failsafe,
                # PX4: the estimator has settled and arming is allowed (sitl_mock.px4)
                "ready": self.px4.ready if self.px4 is not None else True,
            }

    def _set_group(self, group: int, hz: float) -> None:
        """ArduPilot: one legacy stream group at `hz` (0: stopped)."""
        groups = list(APM_GROUPS) if group == mav.MAV_DATA_STREAM_ALL else [group]
        for g in groups:
            if g not in APM_GROUPS:
                continue
            for mid in APM_GROUPS[g][1]:
                self.intervals[mid] = max(1.0 / hz, self.dt) if hz > 0 else math.inf
                self.next_due[mid] = self.t

    # ------------------------------------------------------------------ sending

    def _send(self, msg: Any) -> None:
        if self.t < self.rebooting_until or not self.link_faults.admit(self.t, "out"):
            return
        data = self.enc.encode(msg)
        if self.link_faults.latency_s > 0:
            self.link_faults.push(self.t, ("out", data))
            return
        for link in self.links:
            link.send(data)

    def _text(self, severity: int, text: str) -> None:
        self.log.write("event", self.t, event="statustext", severity=severity, text=text)
        self._send(tm.statustext(self.enc.mav, severity, text))

    def _report(self, severity: int, text: str, event: str | None, args: bytes = b"",
                internal: int | None = None) -> None:
        """What an autopilot tells the ground: PX4 >= 1.14 an EVENT (none if `event` is None,
        as PX4 reports plain mode changes and rejected setpoints on its console only), else
        STATUSTEXT. `severity` is the external log level (MAV_SEVERITY numbering)."""
        if not self.events:
            self._text(severity, text)
            return
        if event is None:
            return
        seq = self.event_seq
        self.event_seq = (self.event_seq + 1) & 0xFFFF
        self.log.write("event", self.t, event="px4_event", name=event, id=px4_events.IDS[event],
                       level=px4_events.LEVELS[severity], sequence=seq, text=text)
        self._send(tm.event(self.enc.mav, event, severity, seq, self.time_boot_ms, args, internal))
