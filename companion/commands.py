"""Operator commands as explicit sequences: arm, takeoff, start, hold, resume, land, abort, disarm.

Which command is accepted in which state is `Flight.refuse` (the table is in the README);
the sequences here talk to the autopilot through the MAVLink adapter, hand control to and
from `Control`, and missions to `Navigator`. A sequence that fails says why (`refused`,
with the autopilot's answer) and leaves the vehicle in a state it can be commanded from.
"""

from __future__ import annotations

import asyncio
import logging
import math
from typing import Any

import numpy as np

from companion.config import Config
from companion.control import Control
from companion.flight import HOLDING_CONTROL, Flight, State
from companion.navigator import Navigator
from companion.report import Reporter
from companion.wire.mavlink import CommandFailed, MavlinkLink
from companion.wire.messages import Command, bounds_from
from planner_core import Problem, allocate_times, plan, splice

log = logging.getLogger("companion")
S = State
MAV_LANDED_IN_AIR = 2


class Commands:
    def __init__(self, cfg: Config, flight: Flight, control: Control, link: MavlinkLink, navigator: Navigator,
                 report: Reporter) -> None:
        self.cfg = cfg
        self.flight = flight
        self.control = control
        self.link = link
        self.nav = navigator
        self.report = report
        self.task: asyncio.Task[None] | None = None  # the running arm/takeoff/start sequence

    def cancel_sequence(self) -> None:
        if self.task is not None and self.task is not asyncio.current_task() and not self.task.done():
            self.task.cancel()

    def take_control(self, reason: str) -> None:
        st = self.link.state
        self.control.take(st.position, float(st.attitude[2]), reason)
        self.flight.exit_requested = False

    def release_control(self) -> None:
        """Stop commanding at once; what is left of the mission waits for `start`."""
        self.nav.release()
        self.control.release()
        self.cancel_sequence()

    # -- dispatch -------------------------------------------------------------------------------

    async def on_command(self, cmd: Command, arrived: float) -> None:
        name, st = cmd.name, self.link.state
        why = self.flight.refuse(name, armed=st.armed, auto_arm=self.cfg.safety.auto_arm,
                                 has_mission=self.nav.has_mission(),
                                 reported_in_air=st.landed_state == MAV_LANDED_IN_AIR)
        if why is None and st.last_heartbeat == -math.inf:
            why = "no autopilot heartbeat yet"
        if why is None and name in ("arm", "takeoff", "start") and not st.has_position:
            why = "no position estimate from the autopilot"
        if why is not None:
            self.report.refuse(name, why)
            return
        self.report.event("accepted", f"command {name}", key="command", command=name)
        if name in ("arm", "takeoff", "start"):
            self.cancel_sequence()
            body = {"arm": self.arm, "takeoff": lambda: self.takeoff(cmd.altitude or self.cfg.safety.takeoff_altitude),
                    "start": lambda: self.start(arrived)}[name]()
            self.task = asyncio.create_task(self._sequence(name, body))
        elif name == "hold":
            await self.nav.hold("hold command", arrived)
        elif name == "resume":
            await self.nav.resume(arrived)
        elif name == "land":
            await self.land()
        elif name == "abort":
            await self.abort(arrived)
        elif name == "disarm":
            await self.disarm()

    async def _sequence(self, name: str, coro: Any) -> None:
        try:
            await coro
        except CommandFailed as exc:
            self.report.refuse(name, f"failed: {exc}")
            if self.flight.state in (S.ARMING, S.TAKEOFF):
                self.nav.release()
                self.control.release()
                self.report.go(S.IDLE if not self.link.state.armed else S.FAILSAFE, f"{name} failed: {exc}")
        except asyncio.CancelledError:
            pass

    # -- sequences -------------------------------------------------------------------------------

    async def _take_follow_mode(self, reason: str) -> None:
        """Stream a hold at the measured position, then ask for OFFBOARD/GUIDED."""
        st = self.link.state
        self.report.go(S.ARMING, reason)
        if st.autopilot == "px4":
            self.take_control(reason)
            # PX4 refuses OFFBOARD unless setpoints have been streaming for a while.
            await asyncio.sleep(1.1)
        await self.link.set_follow_mode()
        await self.link.wait_for(lambda s: s.in_follow_mode(), 3.0, "the autopilot to confirm OFFBOARD/GUIDED")
        if st.autopilot != "px4" and self.flight.airborne:
            self.take_control(reason)

    async def arm(self) -> None:
        await self._take_follow_mode("arm command")
        self.flight.disarm_requested = False
        await self.link.arm(True)
        await self.link.wait_for(lambda s: s.armed, 3.0, "the autopilot to report armed")
        where = "in the air" if self.flight.airborne else "on the ground"
        self.report.go(S.READY, f"armed in {self.link.state.mode} ({where}): holding")

    async def takeoff(self, altitude: float) -> None:
        st = self.link.state
        if not st.armed:
            await self.arm()
        elif self.flight.state not in (S.READY, S.HOLDING):
            await self._take_follow_mode("takeoff command")
        ground = st.position.copy()
        target = ground + np.array([0.0, 0.0, -altitude])
        self.report.go(S.TAKEOFF, f"taking off to {altitude:.2f} m")
        tol = self.cfg.safety.arrival_tolerance
        if st.autopilot == "px4":
            await self._px4_climb(target)
        else:
            self.control.pause()
            await self.link.takeoff(altitude)
            await self.link.wait_for(lambda s: s.position[2] <= target[2] + tol, 10.0 + altitude / 0.3,
                                     f"altitude {altitude:.2f} m")
            self.take_control("takeoff complete")
        self.flight.airborne = True
        self.report.go(S.READY, f"airborne at {altitude:.2f} m: holding")
        pending = self.nav.pending
        if pending is not None and pending.autostart and not self.flight.starting:
            await self.nav.fly(pending, None)

    async def _px4_climb(self, target: np.ndarray) -> None:
        """A verified vertical climb streamed in OFFBOARD (PX4 has no GUIDED-style takeoff for us)."""
        base = self.control.active
        assert base is not None
        t_split = self.control.now() + self.cfg.planner.split_ahead
        jet = base.jet(t_split)
        bounds = bounds_from(None, self.cfg)
        points = np.vstack([jet[0], target])
        times = allocate_times(points, bounds, t0=t_split)
        problem = Problem.from_waypoints(points, np.diff(times), bounds, initial=jet, t0=t_split)
        result = await self.nav.runtime.plan(plan, problem)
        if not result.ok or result.trajectory is None:
            raise CommandFailed(f"no verified climb: {result.message}")
        if not self.control.swap(splice(base, result.trajectory), t_split, None, "takeoff"):
            raise CommandFailed("climb planning was too slow")
        tol = self.cfg.safety.arrival_tolerance
        end = result.trajectory.t_end
        await self.link.wait_for(
            lambda s: self.control.flying and self.control.now() >= end and abs(s.position[2] - target[2]) <= tol,
            end - self.control.now() + 10.0, "the climb to finish")

    async def start(self, arrived: float) -> None:
        self.flight.starting = True
        try:
            await self._start(arrived)
        finally:
            self.flight.starting = False

    async def _start(self, arrived: float) -> None:
        st = self.link.state
        if not st.armed:
            await self.takeoff(self.cfg.safety.takeoff_altitude)
        elif self.flight.state in (S.PILOT, S.FAILSAFE, S.IDLE):
            if not self.flight.airborne and st.landed_state != MAV_LANDED_IN_AIR and st.autopilot != "px4":
                raise CommandFailed("vehicle is on the ground: send 'takeoff' first")
            await self._take_follow_mode("start command: taking control")
            self.report.go(S.READY, f"in control ({self.link.state.mode}): holding")
        if self.flight.state is S.READY and not self.flight.airborne:
            await self.takeoff(self.cfg.safety.takeoff_altitude)
        nav = self.nav
        if nav.pending is not None:
            await nav.fly(nav.pending, arrived)
        elif nav.interrupted is not None:
            await nav.resume(arrived)

    async def land(self) -> None:
        """The autopilot lands (NAV_LAND / LAND mode), from any state in which the vehicle may
        be in the air: our modes, a pilot's, a failsafe's, or after a restart."""
        self.cancel_sequence()
        self.flight.exit_requested = True
        self.nav.forget()
        self.control.release()
        was = self.flight.state
        self.report.go(S.LANDING, f"land command ({was.value}): the autopilot lands")
        try:
            await self.link.land()
        except CommandFailed as exc:
            self.report.refuse("land", f"failed: {exc}")

    async def abort(self, arrived: float) -> None:
        self.cancel_sequence()
        state = self.flight.state
        if state in HOLDING_CONTROL or (state is S.TAKEOFF and self.control.streaming):
            await self.nav.abort(arrived)
        else:
            self.nav.forget()
            if state in (S.ARMING, S.TAKEOFF):
                self.control.release()
                self.report.go(S.IDLE if not self.link.state.armed else S.FAILSAFE, "abort command")
        self.report.event("aborted", "mission and pending commands cancelled")

    async def disarm(self) -> None:
        self.flight.disarm_requested = True
        self.release_control()
        try:
            await self.link.arm(False)
        except CommandFailed as exc:
            self.report.refuse("disarm", f"failed: {exc}")
            return
        self.flight.landed()
        self.report.go(S.IDLE, "disarmed on command")
