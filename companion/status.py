"""The status document: what `<prefix>/<vehicle>/status` says, put together from the parts
that own each figure (the supervisor, the link, control, the navigator, tracking, ...).

Read-only: building it changes nothing. Published periodically and when an event changed it
(the service's status loop), and answered to a status query.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any

import numpy as np

from companion.config import Config
from companion.control import Control
from companion.deconfliction import Deconfliction
from companion.fleet import FleetFrame
from companion.limits_watch import LimitsWatch
from companion.navigator import Navigator
from companion.runtime import GcPacer
from companion.sendproc import SetpointProcess
from companion.setpoints import SetpointSender
from companion.stalls import StallWatch
from companion.supervisor import Supervisor
from companion.tap import Tap
from companion.tracking import Tracking
from companion.wire import encode as enc
from companion.wire.mavlink import MavlinkLink
from companion.wire.messages import fence_at_home


class StatusReport:
    def __init__(self, cfg: Config, *, flight: Supervisor, link: MavlinkLink, control: Control,
                 navigator: Navigator, tracking: Tracking, sender: SetpointSender | SetpointProcess,
                 limits: LimitsWatch, gc: GcPacer, stalls: StallWatch, tap: Tap, fleet: FleetFrame,
                 deconfliction: Deconfliction, session: Callable[[], str | None]) -> None:
        self.cfg = cfg
        self.flight = flight
        self.link = link
        self.control = control
        self.navigator = navigator
        self.tracking = tracking
        self.sender = sender
        self.limits = limits
        self.gc = gc
        self.stalls = stalls
        self.tap = tap
        self.fleet = fleet
        self.deconfliction = deconfliction
        self.session = session  # the Zenoh session's id, once open

    def build(self) -> dict[str, Any]:
        st, ctl = self.link.state, self.control
        # measured position against the setpoint of the measurement's own time (Tracking)
        tracking_error = self.tracking.tracking_error if ctl.streaming else None
        return {
            "vehicle": self.cfg.vehicle.id,
            "session": self.session(),
            "time": round(time.time(), 3),
            "state": self.flight.state.value,
            "airborne": self.flight.airborne,
            "autopilot": st.autopilot,
            "mode": st.mode,
            # a disarmed PX4 reports its last user mode (OFFBOARD after an offboard landing):
            # that flies nothing
            "active_mode": st.mode if st.armed else None,
            "armed": st.armed,
            "origin": "local",
            "home": enc.vec(st.home) if st.home is not None else None,
            # a usable LOCAL_POSITION_NED: real ArduCopter reports home ~22 s before its first one
            "position_ok": st.position_problem() is None,
            "geofence": self._geofence(),
            "ground_z": enc.num(self.flight.ground_z),
            "link": self.link.link_ok() if self.flight.seen_link else False,
            "streaming": ctl.streaming,
            **self.navigator.status_fields(),
            "tracking_error": enc.num(tracking_error),
            "tracking_error_max": enc.num(self.tracking.tracking_error_max),
            "lead_ms": round(self.sender.lead * 1000, 1),
            "lag_estimate_ms": enc.ms(self.tracking.lag_estimate),
            # the aim beyond the plan ([setpoints] accel_lead, per autopilot with "autopilot"): k, s²
            # and its low-pass time constant, s; 0 and 0: none
            "accel_lead": self.sender.accel_lead,
            "accel_lead_tc": self.sender.accel_lead_tc,
            # its horizontal terms ([setpoints] aim_horizontal): [[k s², tc s], ...]
            "aim_horizontal": [list(term) for term in getattr(self.sender, "aim_horizontal", ())],
            # the allowance in use, and whose: `[planner] tracking_allowance` or the autopilot's default
            "tracking_allowance": self.tracking.allowance()[0],
            "tracking_allowance_from": self.tracking.allowance()[1],
            **self._limits_status(),
            "message_to_setpoint_ms": enc.ms(ctl.setpoint_latency),
            "setpoints_sent": self.link.sent_setpoints,
            "setpoint_gap_max_ms": round(ctl.setpoint_gap_max * 1000, 2),
            "setpoint_period_ms": ctl.period_stats(),
            "gc_pause_max_ms": round(self.gc.worst * 1000, 2),
            "setpoints_stalled": self.stalls.setpoints_stalled,
            **self.tap.status_fields(),
            "mavlink_ignored": dict(self.link.gate.ignored) if self.link.gate is not None else {},
            "fleet": self._fleet_status(),
        }

    def _fleet_status(self) -> dict[str, Any] | None:
        st = self.fleet.status()
        sep = self.deconfliction.status()
        return st if st is None or sep is None else {**st, "deconfliction": sep}

    def _limits_status(self) -> dict[str, Any]:
        """The autopilot's limits (each with its source) and the bounds flown because of them."""
        lim = self.limits.assumed()
        b = self.limits.default_bounds()
        return {
            "autopilot_limits": None if lim is None else {
                **lim.as_status(), "read": self.limits.limits is not None, "headroom": self.limits.headroom},
            "bounds_flown": {name: {"lo": [round(float(x), 4) for x in b.lo[i]],
                                    "hi": [round(float(x), 4) for x in b.hi[i]],
                                    "horizontal": enc.num(float(b.horizontal[i]))}
                             for i, name in enumerate(("velocity", "acceleration", "jerk", "snap"))},
        }

    def _geofence(self) -> dict[str, Any]:
        """The geofence box in use, in the local frame, and what it is relative to."""
        home = self.link.state.home
        fence = fence_at_home(self.cfg, home).geofence
        follows = self.cfg.geofence.origin == "home" and home is not None
        return {"min": enc.vec(np.asarray(fence.min)), "max": enc.vec(np.asarray(fence.max)),
                "relative_to": "home" if follows else "local"}
