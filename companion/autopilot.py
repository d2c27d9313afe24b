"""What the autopilot reports, and how the vehicle's situation follows it.

Heartbeats (mode, armed), the landed state, STATUSTEXT and link loss update `Flight`; a mode
we did not ask for is a pilot takeover and a disarm we did not ask for a failsafe: control
is released at once and never retaken without a new `start`.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

from companion.config import Config
from companion.flight import IN_OUR_MODE, Flight, State, on_mode_report
from companion.report import Reporter
from companion.wire.mavlink import MavlinkLink

S = State
MAV_LANDED_ON_GROUND = 1
MAV_LANDED_IN_AIR = 2
MAV_LANDED_TAKEOFF = 3
MAV_LANDED_LANDING = 4


class AutopilotWatch:
    def __init__(self, cfg: Config, flight: Flight, link: MavlinkLink, report: Reporter,
                 release_control: Callable[[], None]) -> None:
        self.cfg = cfg
        self.flight = flight
        self.link = link
        self.report = report
        self.release_control = release_control

    def on_message(self, kind: str, msg: Any) -> None:
        if kind == "HEARTBEAT":
            self.on_heartbeat()
        elif kind == "EXTENDED_SYS_STATE":
            self.on_landed_state(int(msg.landed_state))
        elif kind == "STATUSTEXT":
            self.report.event("autopilot", f"autopilot says: {msg.text}", severity=int(msg.severity))

    def on_landed_state(self, landed: int) -> None:
        fl = self.flight
        if landed in (MAV_LANDED_IN_AIR, MAV_LANDED_LANDING):
            fl.airborne = True
        elif landed == MAV_LANDED_ON_GROUND and fl.state is not S.TAKEOFF and fl.airborne:
            # Our own takeoff sets `airborne` when it completes; otherwise the autopilot knows.
            fl.landed()
            self.report.dirty = True

    def on_heartbeat(self) -> None:
        st, fl = self.link.state, self.flight
        if not fl.seen_link:
            fl.seen_link = True
            self.report.event("link", f"autopilot found: {st.autopilot} in {st.mode}", autopilot=st.autopilot,
                              mode=st.mode)
        if fl.link_lost:
            fl.link_lost = False
            self.report.event("link_restored", f"MAVLink link restored: autopilot in {st.mode}, "
                              f"{'armed' if st.armed else 'disarmed'}; send 'start' to take control again",
                              mode=st.mode, armed=st.armed)
        state = fl.state
        reaction = on_mode_report(state, st.in_follow_mode(), fl.exit_requested)
        if reaction is not None:
            self.release_control()
            self.report.go(reaction[0], f"{reaction[1]} (mode {st.mode})")
            self.report.event("pilot_takeover", f"autopilot switched to {st.mode}: stopped commanding; "
                              "send 'start' to take control again", mode=st.mode)
            return
        if not st.armed:
            if state in IN_OUR_MODE and not fl.disarm_requested:
                self.release_control()
                fl.landed()
                self.report.go(S.IDLE, "the autopilot disarmed the vehicle")
                self.report.event("failsafe", "the autopilot disarmed the vehicle", mode=st.mode)
            elif state in (S.LANDING, S.PILOT, S.FAILSAFE):
                fl.landed()
                self.report.go(S.IDLE, "landed and disarmed" if state is S.LANDING
                               else f"the vehicle disarmed ({state.value} before)")
            elif state is S.IDLE:
                fl.landed()
        self.report.dirty = True

    def check_link(self) -> None:
        fl = self.flight
        if not fl.seen_link or fl.link_lost or self.link.link_ok():
            return
        fl.link_lost = True
        was = fl.state
        if fl.controlling:
            self.release_control()
            self.report.go(S.FAILSAFE, "MAVLink link lost: no autopilot heartbeat")
        self.report.event("link_lost", f"MAVLink link lost (no heartbeat for {self.cfg.mavlink.link_timeout} s) "
                          f"while {was.value}; stopped commanding", previous_state=was.value)
