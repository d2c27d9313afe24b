"""Operator commands as explicit sequences: arm, takeoff, start, hold, resume, land, abort, disarm.

Which command is accepted in which state is `FlightState.refuse` (the table is in the README);
the sequences here talk to the autopilot through the MAVLink adapter, hand control to and
from `Control`, and missions to `Navigator`. A sequence that fails says why (`refused`,
with the autopilot's answer) and leaves the vehicle in a state it can be commanded from.
Leaving the vehicle to the autopilot (on exit, after a stall) is `handover.py`'s; the
tracking error and the setpoints' lead are `tracking.py`'s.
"""

from __future__ import annotations

import asyncio
import logging
import math
import time
from collections.abc import Iterable
from dataclasses import replace
from typing import Any

import numpy as np

from companion.config import Config
from companion.control import SWAP_LATE, Control
from companion.flight import HOLDING_CONTROL, State
from companion.handover import at_rest
from companion.navigator import Navigator
from companion.plan_budget import MAX_AHEAD, RETRY_MARGIN
from companion.report import Reporter
from companion.runtime import Runtime
from companion.supervisor import (
    Armed,
    ArmRequested,
    ControlTaken,
    ControlTakenBack,
    DisarmedOnCommand,
    DisarmRequested,
    LandRequested,
    SequenceAborted,
    StartBegan,
    StartEnded,
    Supervisor,
    TakeoffBegan,
    TakingControl,
    TookOff,
)
from companion.wire.mavlink import MavlinkLink
from companion.wire.messages import Command
from companion.wire.px4_events import arming_report
from companion.wire.vehicle import MAV_LANDED_IN_AIR, MAV_LANDED_ON_GROUND, CommandFailed, Note
from planner_core import (
    Problem,
    allocate_times,
    held_still,
    plan,
    shifted,
    splice,
    takeoff_duration,
)

log = logging.getLogger("companion")
S = State


class Commands:
    def __init__(self, cfg: Config, flight: Supervisor, control: Control, link: MavlinkLink, navigator: Navigator,
                 report: Reporter, runtime: Runtime | None = None) -> None:
        self.cfg = cfg
        self.flight = flight
        self.control = control
        self.link = link
        self.nav = navigator
        self.report = report
        self.runtime = runtime  # the planner's workers (the takeoff climb)
        self.task: asyncio.Task[None] | None = None  # the running arm/takeoff/start sequence
        # PX4's EVENTs heard (the service shares AutopilotWatch's): the last arming-check report
        self.events_heard: Iterable[Note] = link.state.notes

    def cancel_sequence(self) -> None:
        if self.task is not None and self.task is not asyncio.current_task() and not self.task.done():
            self.task.cancel()

    def take_control(self, reason: str) -> None:
        st = self.link.state
        self.control.take(st.position, float(st.attitude[2]), reason)
        self.flight.handle(ControlTaken())

    def release_control(self) -> None:
        """Stop commanding at once; what is left of the mission waits for `start`."""
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
        if why is None and name in ("arm", "takeoff", "start"):
            why = st.position_problem()
        if why is not None:
            self.report.refuse(name, why, by="companion")
            return
        self.report.event("accepted", f"command {name}", key="command", command=name)
        if name == "takeoff" and cmd.origin == "home" and st.home is None:
            self.report.refuse(name, "a takeoff altitude above home needs HOME_POSITION, which the autopilot has "
                               "not reported yet (send it without origin: above the ground where the vehicle stands)",
                               by="companion")
            return
        if name in ("arm", "takeoff", "start"):
            self.cancel_sequence()
            if name == "arm":
                body = self.arm()
            elif name == "takeoff":
                body = self.takeoff(cmd.altitude or self.cfg.safety.takeoff_altitude, cmd.origin)
            else:
                body = self.start(arrived)
            self.task = asyncio.create_task(self._sequence(name, body))
            return
        done = True
        if name == "hold":
            await self.nav.hold("hold command", arrived)
        elif name == "resume":
            await self.nav.resume(arrived)
            done = self.nav.interrupted is None
        elif name == "land":
            if await self.land():
                # `completed` once the vehicle is on the ground, not when the landing starts
                self.task = asyncio.create_task(self._sequence(name, self._until_on_ground()))
            return
        elif name == "abort":
            await self.abort(arrived)
        elif name == "disarm":
            done = await self.disarm()
        if done:
            self._completed(name)

    def _completed(self, name: str) -> None:
        """The command did what it says (`python -m companion send` exits 0 on this)."""
        self.report.event("completed", f"command {name} done ({self.flight.state.value})", key="command",
                          command=name)

    async def _sequence(self, name: str, coro: Any) -> None:
        try:
            await coro
        except CommandFailed as exc:
            # the companion's own checks say why; the autopilot's refusals say what failed
            reason = str(exc) if exc.by == "companion" else f"failed: {exc}"
            extra: dict[str, Any] = {}
            if exc.by == "autopilot" and exc.result is not None and name in ("arm", "takeoff", "start"):
                checks = arming_report(self.events_heard, time.monotonic())
                if checks is not None and checks[1]:
                    age, said = checks
                    reason += f"; PX4's arming checks ({age:.1f} s before): {'; '.join(said)}"
                    exc.reasons = tuple(dict.fromkeys((*exc.reasons, *said)))
                    extra["arming_checks"] = {"age_s": round(age, 2), "reasons": list(said)}
            self.report.refuse(name, reason, by=exc.by, **exc.fields(), **extra)
            self.flight.handle(SequenceAborted(f"{name} failed: {exc}", armed=self.link.state.armed))
        except asyncio.CancelledError:
            self.report.refuse(name, "cancelled before it completed", by="companion")
        else:
            self._completed(name)

    # -- sequences -------------------------------------------------------------------------------

    async def _take_follow_mode(self, reason: str) -> None:
        """Stream a hold at the measured position, then ask for OFFBOARD/GUIDED."""
        st = self.link.state
        self.flight.handle(TakingControl(reason))
        if st.autopilot == "px4":
            sent = self.link.sent_setpoints
            self.take_control(reason)
            # PX4 refuses OFFBOARD unless setpoints have been streaming for a while (COM_OF_LOSS_T-
            # based, 1 s in the docs): counted from the first setpoint that left, not from when
            # we asked for the stream, which a busy computer may start a few hundred ms late.
            started = time.monotonic() + 3.0
            while self.link.sent_setpoints == sent and time.monotonic() < started:
                await asyncio.sleep(0.005)
            await asyncio.sleep(1.1)
        await self.link.set_follow_mode()
        await self.link.wait_for(lambda s: s.in_follow_mode(), 3.0, "the autopilot to confirm OFFBOARD/GUIDED")
        if st.autopilot != "px4" and self.flight.airborne:
            self.take_control(reason)

    async def arm(self) -> None:
        st = self.link.state
        before = (st.base_mode, st.custom_mode, st.mode)
        await self._take_follow_mode("arm command")
        self.flight.handle(ArmRequested())
        try:
            await self.link.arm(True)
            await self.link.wait_for(lambda s: s.armed, 3.0, "the autopilot to report armed")
        except CommandFailed as exc:
            if st.armed or not before[2] or st.mode == before[2]:
                raise
            # Denied: leave the autopilot in the mode it was in, not in OFFBOARD/GUIDED.
            try:
                await self.link.restore_mode(before[0], before[1])
                await self.link.wait_for(lambda s: s.mode == before[2], 3.0, f"the autopilot to confirm {before[2]}")
            except CommandFailed as again:
                raise exc.chained(f"{exc}; and the previous mode {before[2]} was not restored: {again}") from exc
            raise exc.chained(f"{exc}; the autopilot is back in {before[2]}") from exc
        self.flight.handle(Armed(self.link.state.mode))

    def takeoff_target(self, altitude: float, origin: str = "ground") -> tuple[np.ndarray, str]:
        """Where a takeoff to `altitude` ends (NED, local frame), and what it is above.

        Above the ground where the vehicle stands (the z it last stood at disarmed, or where it
        is when on the ground), or above home (`origin` "home"): never `z = -altitude` in the
        local frame, whose origin is not the ground (PX4's ground is often at z = +1.5 m)."""
        st, fl = self.link.state, self.flight
        here = st.position.copy()
        if origin == "home" and st.home is not None:
            return np.array([here[0], here[1], float(st.home[2]) - altitude]), "home"
        on_ground = not fl.airborne and st.landed_state != MAV_LANDED_IN_AIR
        if on_ground or fl.ground_z is None:
            return here + np.array([0.0, 0.0, -altitude]), "the ground"
        return np.array([here[0], here[1], fl.ground_z - altitude]), "the ground"

    async def takeoff(self, altitude: float, origin: str = "ground") -> None:
        st = self.link.state
        if not st.armed:
            await self.arm()
        elif self.flight.state not in (S.READY, S.HOLDING):
            await self._take_follow_mode("takeoff command")
        target, above = self.takeoff_target(altitude, origin)
        self.flight.handle(TakeoffBegan(f"taking off to {altitude:.2f} m above {above} (local z {target[2]:.2f} m NED)"))
        tol = self.cfg.safety.arrival_tolerance
        if st.autopilot == "px4":
            await self._px4_climb(target)
        else:
            self.control.pause()
            # ArduPilot's takeoff altitude is above home
            home_z = float(st.home[2]) if st.home is not None else float(st.position[2])
            await self.link.takeoff(max(0.1, home_z - float(target[2])))
            rest = self.cfg.safety.rest_speed
            await self.link.wait_for(lambda s: abs(s.position[2] - target[2]) <= tol and at_rest(s.velocity, rest),
                                     10.0 + altitude / 0.3, f"altitude {altitude:.2f} m, at rest")
            self.take_control("takeoff complete")
        self.flight.handle(TookOff(f"airborne at {altitude:.2f} m above {above}: holding"))
        pending = self.nav.pending
        if pending is not None and pending.autostart and not self.flight.starting:
            await self.nav.fly(pending, None)

    async def _px4_climb(self, target: np.ndarray) -> None:
        """A verified vertical climb streamed in OFFBOARD (PX4 has no GUIDED-style takeoff for us)."""
        bounds = self.nav.default_bounds()  # within the autopilot's limits
        # split as far ahead as planning takes in this service; a plan that comes late is planned
        # again once, further ahead (as SplitSwap.at_split does for missions)
        ahead = self.nav.budget.split_ahead_for(2)
        for attempt in range(2):
            base = self.control.active
            assert base is not None
            t_split = self.control.committed() + ahead
            jet = base.jet(t_split)
            points = np.vstack([jet[0], target])
            climb = target - jet[0]
            height = float(np.linalg.norm(climb))
            if height > 1e-3 and at_rest(jet[1], self.cfg.safety.rest_speed):
                # the fastest rest-to-rest climb the planner certifies (issue 12); from a moving
                # start the planner's recovery stretches it if it must
                durations = np.array([takeoff_duration(height, bounds, up=tuple(climb / height))])
            else:
                durations = np.diff(allocate_times(points, bounds, t0=t_split))
            problem = Problem.from_waypoints(points, durations, bounds, initial=jet, t0=t_split)
            t0 = time.monotonic()
            assert self.runtime is not None
            result = await self.runtime.plan(plan, problem)
            took = time.monotonic() - t0
            if not result.ok or result.trajectory is None:
                raise CommandFailed(f"no verified climb: {result.message}", by="companion")
            if self.control.swap(splice(base, result.trajectory), t_split, None, "takeoff"):
                break
            if not self.control.flying:
                raise CommandFailed("control was released during the climb's planning", by="companion")
            if self.control.refusal != SWAP_LATE or attempt == 1:
                raise CommandFailed(f"climb not swapped in: {self.control.refusal}"
                                    + (f" (planning took {took:.2f} s, twice)" if attempt == 1 else ""), by="companion")
            ahead = min(max(2.0 * ahead, RETRY_MARGIN * took + 0.1), MAX_AHEAD)
            # planned too late on a busy computer: from a hold the same climb starts later just as
            # well (the curve and its checks do not depend on the time), so it is moved, not replanned
            t_later = self.control.committed() + ahead
            if held_still(base, t_split, t_later) and self.control.swap(
                    splice(base, later := shifted(result.trajectory, t_later - t_split)), t_later, None, "takeoff"):
                result = replace(result, trajectory=later)
                break
        tol, rest = self.cfg.safety.arrival_tolerance, self.cfg.safety.rest_speed
        assert result.trajectory is not None
        end = result.trajectory.t_end
        await self.link.wait_for(
            lambda s: self.control.flying and self.control.now() >= end and abs(s.position[2] - target[2]) <= tol
            and at_rest(s.velocity, rest), end - self.control.now() + 10.0, "the climb to finish, at rest")

    async def start(self, arrived: float) -> None:
        self.flight.handle(StartBegan())
        try:
            await self._start(arrived)
        finally:
            self.flight.handle(StartEnded())

    async def _start(self, arrived: float) -> None:
        st = self.link.state
        if not st.armed:
            await self.takeoff(self.cfg.safety.takeoff_altitude)
        elif self.flight.state in (S.PILOT, S.FAILSAFE, S.IDLE):
            if not self.flight.airborne and st.landed_state != MAV_LANDED_IN_AIR and st.autopilot != "px4":
                raise CommandFailed("vehicle is on the ground: send 'takeoff' first", by="companion")
            await self._take_follow_mode("start command: taking control")
            self.flight.handle(ControlTakenBack(self.link.state.mode))
        if self.flight.state is S.READY and not self.flight.airborne:
            await self.takeoff(self.cfg.safety.takeoff_altitude)
        nav = self.nav
        if nav.pending is not None:
            await nav.fly(nav.pending, arrived)
        elif nav.interrupted is not None:
            await nav.resume(arrived)

    async def land(self) -> bool:
        """The autopilot lands (NAV_LAND / LAND mode), from any state in which the vehicle may
        be in the air: our modes, a pilot's, a failsafe's, or after a restart."""
        self.cancel_sequence()
        self.control.forget()
        self.control.release()
        self.flight.handle(LandRequested())
        try:
            await self.link.land()
        except CommandFailed as exc:
            self.report.refuse("land", f"failed: {exc}", by="autopilot", **exc.fields())
            return False
        return True

    async def _until_on_ground(self) -> None:
        """The landing ends on the ground: disarmed, or EXTENDED_SYS_STATE on-ground (fresh)."""
        st = self.link.state
        height = 0.0 if self.flight.ground_z is None or not st.has_position else \
            max(0.0, self.flight.ground_z - float(st.position[2]))

        def on_ground(s: Any) -> bool:
            return (not s.armed or (s.landed_state == MAV_LANDED_ON_GROUND
                                    and time.monotonic() - s.last_landed_state < 3.0))

        await self.link.wait_for(on_ground, 30.0 + height / 0.3, "the vehicle to be on the ground")

    async def abort(self, arrived: float) -> None:
        self.cancel_sequence()
        state = self.flight.state
        if state in HOLDING_CONTROL or (state is S.TAKEOFF and self.control.streaming):
            await self.nav.abort(arrived)
        else:
            self.control.forget()
            self.flight.handle(SequenceAborted("abort command", armed=self.link.state.armed))
        self.report.event("aborted", "mission and pending commands cancelled")

    async def disarm(self) -> bool:
        self.flight.handle(DisarmRequested())
        self.release_control()
        try:
            await self.link.arm(False)
        except CommandFailed as exc:
            self.report.refuse("disarm", f"failed: {exc}", by="autopilot", **exc.fields())
            return False
        self.flight.handle(DisarmedOnCommand("disarmed on command"))
        return True

