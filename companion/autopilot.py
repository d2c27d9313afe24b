"""What the autopilot reports, and how the vehicle's situation follows it.

Heartbeats (mode, armed), the landed state, STATUSTEXT and link loss update `Flight`; a mode
we did not ask for is a pilot takeover and a disarm we did not ask for a failsafe: control
is released at once and never retaken without a new `start`.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from companion.config import Config
from companion.flight import IN_OUR_MODE, Flight, State, on_mode_report
from companion.report import Reporter
from companion.wire.mavlink import WANTED, MavlinkLink

log = logging.getLogger("companion")
S = State
TELEMETRY_CHECK = 3.0  # s after the requests: what has not arrived by then is reported
WAITING_EVERY = 5.0  # s between "waiting for autopilot heartbeat" lines
MAV_LANDED_ON_GROUND = 1
MAV_LANDED_IN_AIR = 2
MAV_LANDED_TAKEOFF = 3
MAV_LANDED_LANDING = 4
# Where the autopilot sends no landed state (EXTENDED_SYS_STATE), `airborne` follows the
# height above where the vehicle stood disarmed, and the speed.
LANDED_STATE_STALE = 3.0  # s without EXTENDED_SYS_STATE: the landed state is unknown
AIR_HEIGHT = 0.5  # m above the ground: in the air
GROUND_HEIGHT = 0.3  # m: on the ground when also at rest ...
GROUND_SPEED = 0.2  # m/s
GROUND_FOR = 1.0  # ... for this long


class AutopilotWatch:
    def __init__(self, cfg: Config, flight: Flight, link: MavlinkLink, report: Reporter,
                 release_control: Callable[[], None],
                 on_position: Callable[[float], None] | None = None) -> None:
        self.cfg = cfg
        self.flight = flight
        self.link = link
        self.report = report
        self.release_control = release_control
        self.on_position_sample = on_position  # each LOCAL_POSITION_NED, with its arrival time
        self.ground_z: float | None = None  # NED z where the vehicle last stood disarmed
        self._on_ground_since = math.inf
        self._telemetry_task: asyncio.Task[None] | None = None
        self._waiting_said = -math.inf
        self.missing_telemetry: list[str] | None = None  # None: not checked yet

    # -- telemetry, asked for --------------------------------------------------------------

    def ask_telemetry(self, why: str) -> None:
        """Request the messages the companion uses (on link-up, after a reboot) and check, a
        little later, that each arrives."""
        if self._telemetry_task is not None and not self._telemetry_task.done():
            self._telemetry_task.cancel()
        with contextlib.suppress(RuntimeError):  # no running loop (unit tests)
            self._telemetry_task = asyncio.get_running_loop().create_task(self._ask_telemetry(why))

    async def _ask_telemetry(self, why: str) -> None:
        since = time.monotonic()
        try:
            answers = await self.link.request_telemetry()
        except OSError as exc:
            log.warning("telemetry request not sent: %s", exc)
            answers = {}
        await asyncio.sleep(max(0.0, since + TELEMETRY_CHECK - time.monotonic()))
        missing = self.link.missing_telemetry(since)
        self.missing_telemetry = missing
        if not missing:
            self.report.event("telemetry", f"telemetry arriving ({why}): {', '.join(WANTED)}", missing=[],
                              requested={k: v for k, v in WANTED.items()})
            return
        hint = self.link.telemetry_hint(missing)
        said = "; ".join(f"{k}: {v}" for k, v in answers.items() if k in missing)
        msg = (f"the autopilot does not send {', '.join(missing)} ({why}, requested "
               f"{TELEMETRY_CHECK:.0f} s ago{'; it answered ' + said if said else ''}): {hint}")
        log.warning("%s", msg)
        self.report.event("telemetry", msg, missing=missing, answers=answers, hint=hint)

    def on_message(self, kind: str, msg: Any) -> None:
        if kind == "HEARTBEAT":
            self.on_heartbeat()
        elif kind == "LOCAL_POSITION_NED":
            now = time.monotonic()
            self.on_position(now)
            if self.on_position_sample is not None:
                self.on_position_sample(now)
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

    def on_position(self, now: float) -> None:
        """`airborne` from height and speed, while the autopilot sends no landed state."""
        st, fl = self.link.state, self.flight
        if not st.has_position:
            return
        z = float(st.position[2])
        if not st.armed:
            self.ground_z = z
            self._on_ground_since = math.inf
            return
        if now - st.last_landed_state < LANDED_STATE_STALE or self.ground_z is None:
            return
        if fl.state in (S.ARMING, S.TAKEOFF):
            return  # our own takeoff decides when it is complete
        height = self.ground_z - z
        if height > AIR_HEIGHT:
            self._on_ground_since = math.inf
            if not fl.airborne:
                fl.airborne = True
                self.report.dirty = True
            return
        if height < GROUND_HEIGHT and float(np.linalg.norm(st.velocity)) < GROUND_SPEED:
            self._on_ground_since = min(self._on_ground_since, now)
            if fl.airborne and now - self._on_ground_since >= GROUND_FOR:
                fl.landed()
                self.report.dirty = True
        else:
            self._on_ground_since = math.inf

    def on_heartbeat(self) -> None:
        st, fl = self.link.state, self.flight
        if not fl.seen_link:
            fl.seen_link = True
            self.report.event("link", f"autopilot found: {st.autopilot} in {st.mode}", autopilot=st.autopilot,
                              mode=st.mode)
            self.ask_telemetry("link up")
        if fl.link_lost:
            fl.link_lost = False
            self.ask_telemetry("link restored (the autopilot may have rebooted)")
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
        if not fl.seen_link:
            now = time.monotonic()
            if now - self._waiting_said >= WAITING_EVERY:
                first = self._waiting_said == -math.inf
                self._waiting_said = now
                text = f"waiting for autopilot heartbeat on {self.cfg.mavlink.url}"
                log.warning("%s", text)
                if first:
                    self.report.event("link", text, url=self.cfg.mavlink.url)
            return
        if not fl.seen_link or fl.link_lost or self.link.link_ok():
            return
        fl.link_lost = True
        was = fl.state
        if fl.controlling:
            self.release_control()
            self.report.go(S.FAILSAFE, "MAVLink link lost: no autopilot heartbeat")
        self.report.event("link_lost", f"MAVLink link lost (nothing from the autopilot for {self.cfg.mavlink.link_timeout} s) "
                          f"while {was.value}; stopped commanding", previous_state=was.value)
