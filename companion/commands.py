"""Operator commands as explicit sequences: arm, takeoff, start, hold, resume, land, abort, disarm.

Which command is accepted in which state is `FlightState.refuse` (the table is in the README);
the sequences here talk to the autopilot through the MAVLink adapter, hand control to and
from `Control`, and missions to `Navigator`. A sequence that fails says why (`refused`,
with the autopilot's answer) and leaves the vehicle in a state it can be commanded from.
What each sequence does next from what it observed (the autopilot's answer or its timeout, the
mode and armed state, the climb's swap) is decided by one pure function,
companion.command_rules.command_step: the sequences here observe, call it, show the call to the
flight recorder (/commands/step) and carry out the action; the waits themselves stay here.
Leaving the vehicle to the autopilot (on exit, after a stall) is `handover.py`'s; the
tracking error and the setpoints' lead are `tracking.py`'s.
"""

from __future__ import annotations

import asyncio
import itertools
import logging
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from companion import choice_rules as cr
from companion.command_rules import (
    AbortMission,
    Action,
    Aim,
    Aimed,
    Await,
    Begin,
    CheckPending,
    ClimbFrom,
    ClimbMoved,
    ClimbPlanned,
    ClimbSwapped,
    CommandRules,
    CommandState,
    Complete,
    Did,
    Ended,
    Fail,
    Finish,
    FlyPending,
    Forget,
    MoveClimb,
    Observation,
    Pending,
    PlanClimb,
    Refuse,
    Release,
    Run,
    Say,
    Send,
    Stream,
    SwapClimb,
    TakeControl,
    Transition,
    command_step,
)
from companion.config import Config
from companion.control import SWAP_LATE, Control
from companion.flight import State
from companion.handover import at_rest
from companion.navigator import Navigator
from companion.report import Reporter
from companion.rule_run import RuleRun
from companion.runtime import Runtime
from companion.supervisor import (
    Armed,
    ArmRequested,
    ControlTaken,
    ControlTakenBack,
    DisarmedOnCommand,
    DisarmRequested,
    Event,
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
    Trajectory,
    allocate_times,
    held_still,
    plan,
    shifted,
    splice,
    takeoff_duration,
)

log = logging.getLogger("companion")
S = State

# each call of a sequence's rules, shown to the flight recorder (companion.tap.Tap.command_step):
# (run, step, rules, state before, observation, state after, action)
CommandObserver = Callable[[int, int, CommandRules, CommandState, Observation, CommandState, Action], None]


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
        self.calls = itertools.count(1)  # each run of a sequence's rules, numbered for the records of its steps
        # each call of the rules shown to the flight recorder; the service connects its tap
        self.observe: CommandObserver = lambda *_call: None

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
        failure: CommandFailed | None = None
        cancelled = False
        try:
            await coro
        except CommandFailed as exc:
            failure = exc
        except asyncio.CancelledError:
            cancelled = True
        checks = None
        if failure is not None and failure.by == "autopilot" and failure.result is not None:
            checks = arming_report(self.events_heard, time.monotonic())
        said = checks[1] if checks is not None else ()
        ended = Ended(failure is not None, "" if failure is None else str(failure),
                      "" if failure is None else failure.by, failure is not None and failure.result is not None,
                      cancelled, len(said), "; ".join(said), checks[0] if checks is not None else 0.0)
        # how it ended, reported (never suspends: a cancelled task ends here)
        await self._run(CommandRules("outcome", command=name), _Run(failure=failure, checks=checks), ended)

    # -- sequences -------------------------------------------------------------------------------

    async def _take_follow_mode(self, reason: str) -> None:
        """Stream a hold at the measured position, then ask for OFFBOARD/GUIDED."""
        await self._run(CommandRules("follow", reason=reason))

    async def arm(self) -> None:
        await self._run(CommandRules("arm"))

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
        await self._run(CommandRules("takeoff", altitude=altitude), _Run(origin=origin, altitude=altitude))

    async def _px4_climb(self, target: np.ndarray) -> None:
        """A verified vertical climb streamed in OFFBOARD (PX4 has no GUIDED-style takeoff for us)."""
        bounds = self.nav.default_bounds()  # within the autopilot's limits
        # split as far ahead as planning takes in this service; a plan that comes late is planned
        # again once, further ahead (as SplitSwap.at_split does for missions)
        ahead = self.nav.budget.split_ahead_for(2)
        run = _Run(target=target, bounds=bounds, base=self.control.active)
        assert run.base is not None
        await self._run(CommandRules("climb", ahead=ahead, target_z=float(target[2])), run,
                        ClimbFrom(self.control.committed()))

    async def start(self, arrived: float) -> None:
        self.flight.handle(StartBegan())
        try:
            await self._start(arrived)
        finally:
            self.flight.handle(StartEnded())

    async def _start(self, arrived: float) -> None:
        """What `start` does first and then flies is companion.choice_rules' (a start command's run)."""
        st, nav = self.link.state, self.nav
        run = nav.choices.run(cr.StartCommand(self.cfg.safety.takeoff_altitude), cr.ChoiceState())
        action = run.step(cr.Asked(st.armed, self.flight.state.value, self.flight.airborne,
                                   st.landed_state == MAV_LANDED_IN_AIR, st.autopilot or ""))
        while True:
            if isinstance(action, cr.Refuse):
                raise CommandFailed(action.reason, by="companion")
            if isinstance(action, cr.TakeOff):
                await self.takeoff(action.altitude)
            elif isinstance(action, cr.TakeControl):
                await self._take_follow_mode(action.reason)
                self.flight.handle(ControlTakenBack(self.link.state.mode))
            elif isinstance(action, cr.FlyPending):
                assert nav.pending is not None
                await nav.fly(nav.pending, arrived)
                return
            elif isinstance(action, cr.Resume):
                await nav.resume(arrived)
                return
            elif isinstance(action, cr.Nothing):
                return
            action = run.step(cr.Now(self.flight.state.value, self.flight.airborne, nav.pending is not None,
                                     nav.interrupted is not None))

    async def land(self) -> bool:
        """The autopilot lands (NAV_LAND / LAND mode), from any state in which the vehicle may
        be in the air: our modes, a pilot's, a failsafe's, or after a restart."""
        self.cancel_sequence()
        self.control.forget()
        self.control.release()
        return await self._run(CommandRules("land"))

    async def _until_on_ground(self) -> None:
        """The landing ends on the ground: disarmed, or EXTENDED_SYS_STATE on-ground (fresh)."""
        await self._run(CommandRules("on_ground"))

    async def abort(self, arrived: float) -> None:
        self.cancel_sequence()
        await self._run(CommandRules("abort"), _Run(arrived=arrived))

    async def disarm(self) -> bool:
        return await self._run(CommandRules("disarm"))

    # -- the sequences' shell: observe, decide (companion.command_rules), record, carry out -------

    async def _run(self, rules: CommandRules, run: _Run | None = None, first: Observation | None = None) -> bool:
        """One run of a sequence: what to do at each turn is decided by
        companion.command_rules.command_step; this observes, shows each call to the flight
        recorder (/commands/step) and carries the action out. False: land or disarm refused."""
        run = run if run is not None else _Run()
        step = RuleRun(command_step, rules, CommandState(), "commands", next(self.calls), self.observe).step

        action = step(first if first is not None else self._begin())
        while not isinstance(action, Finish):
            if isinstance(action, Fail):
                if action.how == "again" and run.last is not None:
                    raise run.last
                if action.how == "chained" and run.failure is not None:
                    raise run.failure.chained(action.message) from run.failure
                raise CommandFailed(action.message, by=action.by)
            try:
                seen = await self._carry_out(action, run)
            except CommandFailed as exc:
                run.last, run.failure = exc, run.failure or exc
                seen = self._did(exc)
            action = step(seen)
        return action.ok

    def _begin(self) -> Begin:
        st, fl = self.link.state, self.flight
        height = 0.0 if fl.ground_z is None or not st.has_position else \
            max(0.0, fl.ground_z - float(st.position[2]))
        return Begin(st.autopilot or "", st.armed, st.mode, st.base_mode, st.custom_mode, fl.state.value,
                     self.control.streaming, height)

    def _did(self, exc: CommandFailed | None = None) -> Did:
        st = self.link.state
        return Did(exc is not None, "" if exc is None else str(exc), "" if exc is None else exc.by,
                   None if exc is None else exc.result, st.armed, st.mode, self.flight.airborne)

    async def _carry_out(self, action: Action, run: _Run) -> Observation:
        """Do what `action` says; what was seen then (a failure raises CommandFailed)."""
        st, control = self.link.state, self.control
        if isinstance(action, Transition):
            self.flight.handle(_event(action))
        elif isinstance(action, TakeControl):
            if action.stream:  # counted before the stream starts: the first setpoint may leave at once
                run.sent = self.link.sent_setpoints
            self.take_control(action.reason)
        elif isinstance(action, Stream):
            sent = run.sent
            # PX4 refuses OFFBOARD unless setpoints have been streaming for a while (COM_OF_LOSS_T-
            # based, 1 s in the docs): counted from the first setpoint that left, not from when
            # we asked for the stream, which a busy computer may start a few hundred ms late.
            started = time.monotonic() + 3.0
            while self.link.sent_setpoints == sent and time.monotonic() < started:
                await asyncio.sleep(0.005)
            await asyncio.sleep(1.1)
        elif isinstance(action, Send):
            await self._send(action)
        elif isinstance(action, Await):
            await self._await(action)
        elif isinstance(action, Run):
            if action.sequence == "follow":
                await self._take_follow_mode(action.reason)
            elif action.sequence == "arm":
                await self.arm()
            else:
                assert run.target is not None
                await self._px4_climb(run.target)
        elif isinstance(action, Aim):
            run.target, above = self.takeoff_target(run.altitude, run.origin)
            home_z = float(st.home[2]) if st.home is not None else float(st.position[2])
            return Aimed(float(run.target[2]), above, home_z, st.autopilot or "")
        elif isinstance(action, CheckPending):
            run.pending = self.nav.pending
            return Pending(run.pending is not None and run.pending.autostart and not self.flight.starting)
        elif isinstance(action, FlyPending):
            await self.nav.fly(run.pending, None)
        elif isinstance(action, AbortMission):
            await self.nav.abort(run.arrived)
        elif isinstance(action, Forget):
            control.forget()
        elif isinstance(action, Release):
            self.release_control()
        elif isinstance(action, Say):
            self.report.event(action.kind, action.text)
        elif isinstance(action, Refuse):
            self._refuse(action, run)
        elif isinstance(action, Complete):
            self._completed(action.command)
        else:
            return await self._climb(action, run)
        return self._did()

    async def _climb(self, action: Action, run: _Run) -> Observation:
        """The climb's plan from the flown hold, its swap, and the same climb moved later."""
        control, base, result = self.control, run.base, run.result
        assert base is not None
        if isinstance(action, PlanClimb):
            target, bounds, t_split = run.target, run.bounds, action.t_split
            assert target is not None
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
            run.result = result = await self.runtime.plan(plan, problem)
            took = time.monotonic() - t0
            ok = result.ok and result.trajectory is not None
            return ClimbPlanned(ok, result.message, took, float(result.trajectory.t_end) if ok else 0.0)
        assert result is not None and result.trajectory is not None
        if isinstance(action, SwapClimb):
            swapped = control.swap(splice(base, result.trajectory), action.t_split, None, "takeoff")
            refusal, flying = ("", True) if swapped else (control.refusal, control.flying)
            return ClimbSwapped(refusal, flying, control.committed() if refusal == SWAP_LATE and flying else 0.0)
        assert isinstance(action, MoveClimb)
        held = held_still(base, action.t_split, action.t_later)
        if held:
            later = shifted(result.trajectory, action.t_later - action.t_split)
            if control.swap(splice(base, later), action.t_later, None, "takeoff"):
                run.result = replace(result, trajectory=later)
                return ClimbMoved(True, True, 0.0, float(later.t_end))
        run.base = control.active  # planned again from what is flown then
        assert run.base is not None
        return ClimbMoved(held, False, control.committed(), 0.0)

    async def _send(self, action: Send) -> None:
        link, what = self.link, action.command
        if what == "follow_mode":
            await link.set_follow_mode()
        elif what in ("arm", "disarm"):
            await link.arm(what == "arm")
        elif what == "restore_mode":
            await link.restore_mode(action.base, action.custom)
        elif what == "land":
            await link.land()
        elif what == "takeoff":
            self.control.pause()  # ArduPilot flies its takeoff
            await link.takeoff(action.altitude)
        else:
            raise ValueError(f"no MAVLink command {what!r}")

    async def _await(self, a: Await) -> None:
        tol, rest, control = self.cfg.safety.arrival_tolerance, self.cfg.safety.rest_speed, self.control
        timeout = a.timeout
        predicate: Callable[[Any], bool]
        if a.until == "follow":
            predicate = lambda s: s.in_follow_mode()  # noqa: E731
        elif a.until == "armed":
            predicate = lambda s: s.armed  # noqa: E731
        elif a.until == "mode":
            predicate = lambda s: s.mode == a.mode  # noqa: E731
        elif a.until == "altitude":
            predicate = lambda s: abs(s.position[2] - a.z) <= tol and at_rest(s.velocity, rest)  # noqa: E731
        elif a.until == "climb":
            predicate = lambda s: (control.flying and control.now() >= a.end  # noqa: E731
                                   and abs(s.position[2] - a.z) <= tol and at_rest(s.velocity, rest))
            timeout = a.end - control.now() + 10.0
        elif a.until == "on_ground":
            predicate = lambda s: (not s.armed or (s.landed_state == MAV_LANDED_ON_GROUND  # noqa: E731
                                                   and time.monotonic() - s.last_landed_state < 3.0))
        else:
            raise ValueError(f"no wait {a.until!r}")
        await self.link.wait_for(predicate, timeout, a.what)

    def _refuse(self, action: Refuse, run: _Run) -> None:
        exc = run.last or run.failure
        extra: dict[str, Any] = {}
        if action.checks and exc is not None and run.checks is not None:
            age, said = run.checks
            exc.reasons = tuple(dict.fromkeys((*exc.reasons, *said)))
            extra["arming_checks"] = {"age_s": round(age, 2), "reasons": list(said)}
        fields = exc.fields() if exc is not None else {}
        self.report.refuse(action.command, action.reason, by=action.by, **fields, **extra)


@dataclass
class _Run:
    """What one run's shell holds between its steps: what the rules do not decide on."""

    origin: str = "ground"
    altitude: float = 0.0
    arrived: float = 0.0
    target: np.ndarray | None = None
    bounds: Any = None
    base: Trajectory | None = None
    result: Any = None  # the climb's plan (planner_core's result)
    pending: Any = None  # the mission that starts on its own after the takeoff
    failure: CommandFailed | None = None  # the run's first
    last: CommandFailed | None = None
    checks: tuple[float, Any] | None = None  # PX4's arming checks (age, reasons) when the run is an outcome
    sent: int = 0  # setpoints sent when Control took over (Stream waits for the next)


def _event(a: Transition) -> Event:
    """The supervisor event a Transition names."""
    made: dict[str, Callable[[], Event]] = {
        "TakingControl": lambda: TakingControl(a.reason), "ArmRequested": ArmRequested, "Armed": lambda: Armed(a.mode),
        "TakeoffBegan": lambda: TakeoffBegan(a.reason), "TookOff": lambda: TookOff(a.reason),
        "LandRequested": LandRequested, "SequenceAborted": lambda: SequenceAborted(a.reason, armed=a.armed),
        "DisarmRequested": DisarmRequested, "DisarmedOnCommand": lambda: DisarmedOnCommand(a.reason)}
    return made[a.event]()
