"""The operator commands' sequences' decisions (companion.command_rules.command_step), on their
own and against the sequences as they were before they were a function of their own: a copy of
those methods (`_Old`, verbatim) and today's `Commands` run in the same world (the same
autopilot answers and timeouts, states, planning times, swap refusals, holds, arming checks)
make the same MAVLink commands, waits, supervisor transitions, Control and navigator calls and
reports (texts and `by`) in the same order, and end alike (returned, refused, raised)."""

from __future__ import annotations

import asyncio
import itertools
import sys
import time
import types
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st

import companion.commands as cmdmod
from companion.command_rules import (
    COMMANDS,
    ENDED,
    EVENTS,
    WAITS,
    AbortMission,
    Aimed,
    Await,
    Begin,
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
    MoveClimb,
    Pending,
    PlanClimb,
    Refuse,
    Run,
    Send,
    Transition,
    command_step,
)
from companion.commands import Commands
from companion.config import Config
from companion.control import SWAP_DIFFERS, SWAP_LATE
from companion.flight import HOLDING_CONTROL, FlightState, State
from companion.handover import at_rest
from companion.plan_budget import MAX_AHEAD, RETRY_MARGIN
from companion.report import Reporter
from companion.supervisor import (
    Armed,
    ArmRequested,
    DisarmedOnCommand,
    DisarmRequested,
    LandRequested,
    SequenceAborted,
    Supervisor,
    TakeoffBegan,
    TakingControl,
    TookOff,
)
from companion.wire.px4_events import arming_report
from companion.wire.vehicle import MAV_LANDED_ON_GROUND, CommandFailed, VehicleState
from planner_core import (
    Problem,
    allocate_times,
    held_still,
    plan,
    shifted,
    splice,
    takeoff_duration,
)

S = State
SEQUENCES = ("follow", "arm", "takeoff", "climb", "land", "on_ground", "abort", "disarm", "outcome")
FLIGHT = [s.value for s in State]
TEXT = st.sampled_from(["denied", "timed out after 3.0 s waiting for x", "no answer"])
MODES = st.sampled_from(["", "LOITER", "POSCTL", "OFFBOARD", "GUIDED"])


def _observation(rules: CommandRules, data: st.DataObject, s: CommandState) -> Any:
    """Any observation the sequence could make where the rules wait for `s.expect`."""
    d = data.draw
    if s.expect == "begin" and rules.sequence == "climb":
        return ClimbFrom(d(st.floats(0.0, 100.0)))
    if s.expect == "begin" and rules.sequence == "outcome":
        failed = d(st.booleans())
        return Ended(failed, d(TEXT) if failed else "", d(st.sampled_from(["autopilot", "companion"])) if failed else "",
                     d(st.booleans()), d(st.booleans()), d(st.integers(0, 3)), "GPS not ready", d(st.floats(0.0, 9.0)))
    if s.expect == "begin":
        return Begin(d(st.sampled_from(["px4", "ardupilot"])), d(st.booleans()), d(MODES), d(st.integers(0, 255)),
                     d(st.integers(0, 2**32 - 1)), d(st.sampled_from(FLIGHT)), d(st.booleans()),
                     d(st.floats(0.0, 50.0)))
    if s.expect == "did":
        failed = d(st.sampled_from([False, False, True]))
        return Did(failed, d(TEXT) if failed else "", "autopilot" if failed else "",
                   d(st.sampled_from([None, "MAV_RESULT_DENIED"])) if failed else None, d(st.booleans()), d(MODES),
                   d(st.booleans()))
    if s.expect == "aimed":
        return Aimed(d(st.floats(-50.0, 2.0)), d(st.sampled_from(["the ground", "home"])), d(st.floats(-2.0, 2.0)),
                     d(st.sampled_from(["px4", "ardupilot"])))
    if s.expect == "pending":
        return Pending(d(st.booleans()))
    if s.expect == "planned":
        return ClimbPlanned(d(st.sampled_from([True, True, False])), "no plan", d(st.floats(0.0, 3.0)),
                            d(st.floats(0.0, 100.0)))
    if s.expect == "swapped":
        return ClimbSwapped(d(st.sampled_from(["", SWAP_LATE, SWAP_LATE, SWAP_DIFFERS])), d(st.booleans()),
                            d(st.floats(0.0, 100.0)))
    assert s.expect == "moved"
    moved = d(st.booleans())
    return ClimbMoved(moved or d(st.booleans()), moved, d(st.floats(0.0, 100.0)), d(st.floats(0.0, 100.0)))


RULES = st.builds(CommandRules, st.sampled_from(SEQUENCES), st.sampled_from(["", "arm command"]),
                  st.floats(0.1, 20.0), st.floats(0.01, 3.0), st.floats(-20.0, 2.0),
                  st.sampled_from(["arm", "takeoff", "start", "land"]))


def _drive(rules: CommandRules, data: st.DataObject) -> list[tuple[CommandState, Any, CommandState, Any]]:
    """One run of a sequence, the world drawn: every step (before, observation, after, action)."""
    s, steps = CommandState(), []
    for _ in range(60):
        o = _observation(rules, data, s)
        after, action = command_step(rules, s, o)
        steps.append((s, o, after, action))
        s = after
        if isinstance(action, Finish | Fail):
            assert s.expect == ENDED
            return steps
        assert s.expect != ENDED
    raise AssertionError("the sequence did not end in 60 steps")


@settings(max_examples=400, deadline=None)
@given(RULES, st.data())
def test_every_run_ends_and_each_action_is_one_the_shell_carries_out(rules: CommandRules,
                                                                      data: st.DataObject) -> None:
    """A run ends (Finish or Fail) within a few steps, a failure observed is never let pass (the
    next action fails the run, restores the mode or refuses), and every command, wait and event
    asked for is one the shell knows; after the end, no observation is taken."""
    steps = _drive(rules, data)
    assert len(steps) <= 14
    asked: Any = None  # the action the observation is the outcome of
    for before, o, _after, action in steps:
        if isinstance(action, Send):
            assert action.command in COMMANDS
        if isinstance(action, Await):
            assert action.until in WAITS and action.timeout >= 0.0
        if isinstance(action, Transition):
            assert action.event in EVENTS
        if isinstance(o, Did) and o.failed and isinstance(asked, Send | Await | Run | FlyPending | AbortMission):
            restore = Send("restore_mode", before.before_base, before.before_custom)
            assert isinstance(action, Fail | Refuse) or (action == restore and rules.sequence == "arm")
        asked = action
    with pytest.raises(ValueError):
        command_step(rules, steps[-1][2], steps[-1][1])


@settings(max_examples=300, deadline=None)
@given(st.floats(0.01, 3.0), st.floats(-20.0, 2.0), st.data())
def test_a_climb_is_planned_at_most_twice_and_moved_only_when_late(ahead: float, z: float,
                                                                    data: st.DataObject) -> None:
    """The climb is planned at what is committed plus the lead; a late swap (the first) is moved
    to committed + the lead grown (doubled, or RETRY_MARGIN x what planning took, capped at
    MAX_AHEAD); not moved, planned once more from there; any other refusal, a second late one
    or Control let go fails the takeoff in the companion's words, the second saying "twice"."""
    rules = CommandRules("climb", ahead=ahead, target_z=z)
    steps = _drive(rules, data)
    plans = [(o, a) for _b, o, _a, a in steps if isinstance(a, PlanClimb)]
    assert 1 <= len(plans) <= 2
    assert plans[0][1].t_split == plans[0][0].committed + ahead
    for before, o, after, action in steps:
        if isinstance(action, MoveClimb):
            assert isinstance(o, ClimbSwapped) and o.refusal == SWAP_LATE and o.flying and before.attempt == 0
            assert after.ahead == min(max(2.0 * before.ahead, RETRY_MARGIN * before.took + 0.1), MAX_AHEAD)
            assert action == MoveClimb(before.t_split, o.committed + after.ahead)
        if isinstance(o, ClimbMoved) and not o.moved:
            assert action == PlanClimb(o.committed + before.ahead) and after.attempt == 1
        if isinstance(o, ClimbSwapped) and o.refusal and not isinstance(action, MoveClimb):
            assert isinstance(action, Fail) and action.how == "new" and action.by == "companion"
            assert ("twice" in action.message) == (o.flying and before.attempt == 1)  # any refusal, as before
        if isinstance(action, Await):
            assert action == Await("climb", 0.0, "the climb to finish, at rest", z=z, end=after.end)


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_an_arm_denied_restores_the_mode_it_left_only_when_that_helps(data: st.DataObject) -> None:
    """A denied arm (or no armed report) restores the mode the autopilot was in before OFFBOARD/
    GUIDED, unless it is armed after all, no mode was known or it is still in it; the failure
    then says which; the Armed transition carries the mode seen."""
    steps = _drive(CommandRules("arm"), data)
    begin = steps[0][1]
    for before, o, _after, action in steps:
        if isinstance(action, Send) and action.command == "restore_mode":
            assert isinstance(o, Did) and o.failed and not o.armed and begin.mode and o.mode != begin.mode
            assert (action.base, action.custom) == (begin.base_mode, begin.custom_mode)
        if isinstance(action, Fail) and action.how == "chained":
            assert action.message.startswith(before.denial + "; ") and begin.mode in action.message
        if isinstance(action, Transition) and action.event == "Armed":
            assert isinstance(o, Did) and action.mode == o.mode


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(["arm", "takeoff", "start", "land"]), st.data())
def test_a_command_ends_completed_or_refused_in_the_words_of_who_refused(name: str, data: st.DataObject) -> None:
    steps = _drive(CommandRules("outcome", command=name), data)
    ended, action = steps[0][1], steps[0][3]
    if ended.cancelled:
        assert action == Refuse(name, "cancelled before it completed", "companion")
    elif not ended.failed:
        assert type(action).__name__ == "Complete"
    else:
        checks = ended.by == "autopilot" and ended.result and name != "land" and ended.checks > 0
        assert isinstance(action, Refuse) and action.by == ended.by and action.checks == checks
        assert action.reason.startswith(ended.error if ended.by == "companion" else f"failed: {ended.error}")
        assert ("PX4's arming checks" in action.reason) == checks
        assert Transition("SequenceAborted", f"{name} failed: {ended.error}", armed=steps[1][1].armed) == steps[1][3]


# -- the sequences as they were: the oracle ------------------------------------------------------


class _Old(Commands):
    """Commands' sequences before their decisions were companion.command_rules (commit 5ed79a9),
    verbatim; the names they read are this module's, set to the test's world as the new ones are."""

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



_REAL_SLEEP = asyncio.sleep


@dataclass
class _Answer:
    """The autopilot's answer to one command or wait: it fails (with a MAV_RESULT or without:
    a timeout), or the task is cancelled meanwhile; the armed state and mode it leaves."""

    fail: bool = False
    result: str | None = None
    armed: bool | None = None
    mode: str | None = None
    cancel: bool = False


@dataclass(frozen=True)
class _Traj:
    t_end: float


@dataclass(frozen=True)
class _Result:
    ok: bool
    trajectory: _Traj | None
    message: str = "no verified plan"


@dataclass
class _World:
    """What the sequences read, each value drawn: consumed in order, the same for either."""

    autopilot: str
    armed: bool
    mode: str
    flight: str
    airborne: bool
    streaming: bool
    home: bool
    setpoints_at: float  # when the first setpoint leaves (fake clock; > 3 s: not in time)
    answers: list[_Answer]
    plans: list[tuple[bool, float, float]]  # (ok, took, end)
    refusals: list[str]
    flying: list[bool]
    holds: list[bool]
    autostart: bool | None  # the pending mission's (None: none)
    checks: tuple[float, tuple[str, ...]] | None
    ahead: float
    ops: list[tuple[str, float, str]]  # (command, altitude, origin)
    did: list[tuple[Any, ...]] = field(default_factory=list)
    now: float = 100.0
    taken: int = 0  # Control.take calls

    def run(self, kind: type[Commands], wire: Any = None) -> list[tuple[Any, ...]]:
        """The world's operations by `kind`'s sequences: what was done, in order. `wire(commands,
        supervisor)`: connects them (to a recorder) before."""
        world, did = self, self.did
        answers, plans, refusals = list(self.answers), list(self.plans), list(self.refusals)
        flying, holds = list(self.flying), list(self.holds)

        def answer(what: tuple[Any, ...]) -> None:
            did.append(what)
            a = answers.pop(0) if answers else _Answer()
            if a.armed is not None:
                st.armed = a.armed
            if a.mode is not None:
                st.mode = a.mode
            if a.cancel:
                raise asyncio.CancelledError
            if a.fail:
                raise CommandFailed(f"{what[0]} {what[1]!r}: " + ("denied" if a.result else "no answer"),
                                    result=a.result, reasons=("said before",) if a.result else ())

        st = VehicleState(autopilot=self.autopilot, armed=self.armed, mode=self.mode, base_mode=81, custom_mode=7,
                          last_heartbeat=1.0, landed_state=1)
        st.position = np.array([1.0, 2.0, 0.5])
        st.velocity = np.zeros(3)
        st.home = np.array([0.0, 0.0, 0.3]) if self.home else None

        class Link:
            state = st

            @property
            def sent_setpoints(self) -> int:  # one at each take (the stream starts at once), the rest from then
                return world.taken + int(world.now >= world.setpoints_at)

            async def set_follow_mode(self) -> None:
                mode = st.mode
                st.mode = "OFFBOARD"  # taken, unless the answer says otherwise
                try:
                    answer(("send", "follow_mode"))
                except CommandFailed:
                    st.mode = mode
                    raise

            async def arm(self, value: bool) -> None:
                answer(("send", "arm", value))

            async def restore_mode(self, base: int, custom: int) -> None:
                answer(("send", "restore_mode", base, custom))

            async def land(self) -> None:
                answer(("send", "land"))

            async def takeoff(self, altitude: float) -> None:
                answer(("send", "takeoff", altitude))

            async def wait_for(self, predicate: Any, timeout: float, what: str) -> None:
                answer(("wait", what, timeout, bool(predicate(st)), world.now))

        class Control:
            active: Any = _Traj(0.0)
            t_base = 50.0
            refusal = ""

            @property
            def streaming(self) -> bool:
                return world.streaming

            @property
            def flying(self) -> bool:
                return flying.pop(0) if flying else True

            def now(self) -> float:
                return world.now - self.t_base

            def committed(self) -> float:
                return self.now() + 0.05

            def swap(self, new: Any, t_split: float, arrived: Any, what: str) -> bool:
                self.refusal = refusals.pop(0) if refusals else ""
                did.append(("swap", new.t_end, t_split, arrived, what))
                return not self.refusal

            def take(self, position: Any, yaw: float, reason: str) -> None:
                did.append(("take", tuple(position), yaw, reason))
                world.taken += 1

            def pause(self) -> None:
                did.append(("pause",))

            def release(self) -> None:
                did.append(("release",))

            def forget(self) -> None:
                did.append(("forget",))

        class Base:
            def jet(self, t: float) -> np.ndarray:
                return np.array([[1.0, 2.0, 0.5], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], [0.0, 0.0, 0.0]])

        control = Control()
        control.active = Base()
        pending = None if self.autostart is None else types.SimpleNamespace(autostart=self.autostart)

        class Nav:
            budget = types.SimpleNamespace(split_ahead_for=lambda n: world.ahead)

            @property
            def pending(self) -> Any:
                return pending

            def default_bounds(self) -> str:
                return "bounds"

            async def fly(self, spec: Any, arrived: Any) -> None:
                did.append(("fly", spec is pending, arrived))

            async def abort(self, arrived: float) -> None:
                did.append(("nav abort", arrived))

        class Runtime:
            async def plan(self, fn: Any, problem: Any) -> _Result:
                ok, took, end = plans.pop(0) if plans else (True, 0.01, 60.0)
                did.append(("plan", fn is plan, problem))
                world.now += took
                return _Result(ok, _Traj(end) if ok else None)

        async def sleep(dt: float) -> None:
            world.now += dt
            await _REAL_SLEEP(0)

        def from_waypoints(points: Any, durations: Any, bounds: Any, initial: Any, t0: float) -> tuple[Any, ...]:
            return (points.tolist(), durations.tolist(), bounds, initial.tolist(), t0)

        def held(base: Any, t_split: float, t_later: float) -> bool:
            did.append(("held", t_split, t_later))
            return holds.pop(0) if holds else False

        fake = {
            "time": types.SimpleNamespace(monotonic=lambda: world.now),
            "asyncio": types.SimpleNamespace(**{**vars(asyncio), "sleep": sleep}),
            "arming_report": lambda _notes, _now: world.checks,
            "takeoff_duration": lambda h, b, up: 2.0 * h + up[2],
            "allocate_times": lambda points, bounds, t0: np.array([t0, t0 + 3.0]),
            "Problem": types.SimpleNamespace(from_waypoints=from_waypoints),
            "splice": lambda _base, new: new,
            "held_still": held,
            "shifted": lambda traj, dt: _Traj(traj.t_end + dt),
        }
        fl = Supervisor(FlightState(State(self.flight), self.airborne, seen_link=True, ground_z=0.4))
        real_handle = fl.handle

        def handle(event: Any) -> Any:
            did.append(("transition", event))
            return real_handle(event)

        fl.handle = handle  # type: ignore[method-assign]
        report = Reporter(fl, lambda key, body: did.append(("report", key, tuple(sorted(
            (k, v) for k, v in body.items() if k not in ("t", "time", "stamp", "seq"))))))
        cmds = kind(Config(), fl, control, Link(), Nav(), report, Runtime())  # type: ignore[arg-type]
        if wire is not None:
            wire(cmds, fl)

        async def go() -> None:
            for name, altitude, origin in self.ops:
                try:
                    if name == "land":
                        ok = await cmds.land()
                        did.append(("land returned", ok))
                        if ok:
                            await cmds._sequence(name, cmds._until_on_ground())
                    elif name == "abort":
                        await cmds.abort(7.5)
                    elif name == "disarm":
                        did.append(("disarm returned", await cmds.disarm()))
                    elif name == "follow":
                        await cmds._take_follow_mode("start command: taking control")
                    elif name == "climb":
                        await cmds._px4_climb(np.array([1.0, 2.0, 0.5 - altitude]))
                    else:
                        body = cmds.arm() if name == "arm" else cmds.takeoff(altitude, origin)
                        await cmds._sequence(name, body)
                except (Exception, asyncio.CancelledError) as exc:
                    did.append(("raised", type(exc).__name__, str(exc), getattr(exc, "by", None),
                                getattr(exc, "result", None), getattr(exc, "reasons", None)))
                did.append(("state", fl.value, st.armed, st.mode))

        module = sys.modules[__name__]
        with pytest.MonkeyPatch.context() as mp:
            for name, value in fake.items():
                mp.setattr(cmdmod, name, value)
                mp.setattr(module, name, value)
            asyncio.run(go())
        return did


ANSWER = st.builds(_Answer, st.sampled_from([False, False, False, True]),
                   st.sampled_from([None, "MAV_RESULT_DENIED"]), st.sampled_from([None, None, True, False]),
                   st.sampled_from([None, None, "LOITER", "OFFBOARD"]), st.sampled_from([False] * 15 + [True]))
OPS = st.tuples(st.sampled_from(["arm", "takeoff", "takeoff", "land", "abort", "disarm", "follow", "climb"]),
                st.floats(0.5, 10.0), st.sampled_from(["ground", "home"]))
WORLDS = st.builds(
    _World,
    st.sampled_from(["px4", "ardupilot"]), st.booleans(), st.sampled_from(["", "LOITER", "OFFBOARD", "POSCTL"]),
    st.sampled_from(["IDLE", "READY", "HOLDING", "PILOT", "STREAMING", "TAKEOFF", "FAILSAFE"]),
    st.booleans(), st.booleans(), st.booleans(), st.floats(0.0, 4.0),
    st.lists(ANSWER, min_size=3, max_size=16),
    st.lists(st.tuples(st.sampled_from([True, True, False]), st.floats(0.0, 2.0), st.floats(60.0, 80.0)),
             max_size=3),
    st.lists(st.sampled_from(["", SWAP_LATE, SWAP_LATE, SWAP_DIFFERS]), max_size=4),
    st.lists(st.sampled_from([True, True, True, False]), max_size=8),
    st.lists(st.booleans(), max_size=3),
    st.sampled_from([None, True, False]),
    st.sampled_from([None, (1.25, ()), (2.5, ("GPS not ready", "said before"))]),
    st.floats(0.05, 1.0),
    st.lists(OPS, min_size=1, max_size=3),
)


_OK, _DENIED, _SILENT = _Answer(), _Answer(True, "MAV_RESULT_DENIED"), _Answer(True)


def _world(autopilot: str, answers: list[_Answer], ops: list[tuple[str, float, str]], **kw: Any) -> _World:
    given: dict[str, Any] = {"autopilot": autopilot, "armed": False, "mode": "LOITER", "flight": "IDLE",
                             "airborne": False, "streaming": False, "home": True, "setpoints_at": 100.5,
                             "answers": answers, "plans": [], "refusals": [], "flying": [], "holds": [],
                             "autostart": None, "checks": (1.25, ("GPS not ready",)), "ahead": 0.15, "ops": ops}
    return _World(**{**given, **kw})


@settings(max_examples=300, deadline=None)
@given(WORLDS)
# the rarer paths, always: an arm denied and the mode restored, not restored (refused, or not
# confirmed); a takeoff whose mission then starts on its own; ArduPilot's takeoff; the climb
# late twice
@example(_world("px4", [_OK, _OK, _DENIED, _OK, _OK], [("arm", 1.0, "ground")]))
@example(_world("px4", [_OK, _OK, _SILENT, _DENIED], [("takeoff", 2.0, "ground")]))
@example(_world("ardupilot", [_OK, _OK, _OK, _SILENT, _OK, _SILENT], [("arm", 1.0, "ground"), ("disarm", 0, "")]))
@example(_world("px4", [], [("takeoff", 3.0, "home"), ("land", 0, "")], autostart=True,
                plans=[(True, 0.7, 70.0), (True, 0.9, 72.0)], refusals=[SWAP_LATE, SWAP_LATE], holds=[False]))
@example(_world("ardupilot", [], [("takeoff", 3.0, "home"), ("abort", 0, "")], autostart=True))
def test_the_rules_do_what_the_sequences_did(world: _World) -> None:
    """The same MAVLink commands and waits (with their timeouts, texts and what the wait's
    condition says of the state then), transitions, Control and navigator calls, climb plans
    and swaps, reports (texts, `by`, fields), results and failures, in the same order."""
    old = replace(world, did=[]).run(_Old)
    new = replace(world, did=[]).run(Commands)
    first = next((i for i, (a, b) in enumerate(zip(old, new, strict=False)) if a != b), min(len(old), len(new)))
    assert new == old, f"from {first}: was {old[first:first + 2]}, now {new[first:first + 2]}"


def test_each_step_is_shown_with_its_run_and_number_and_a_failing_observer_changes_nothing() -> None:
    world = _World("px4", False, "LOITER", "IDLE", False, False, False, 0.5, [], [(True, 0.9, 70.0)], [SWAP_LATE],
                   [], [True], None, None, 0.15, [("takeoff", 2.0, "ground")])
    seen: list[tuple[Any, ...]] = []
    real = Commands.__init__

    def init(self: Any, *a: Any) -> None:
        real(self, *a)
        self.observe = lambda *call: seen.append(call)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Commands, "__init__", init)
        did = replace(world, did=[]).run(Commands)
    runs = [c[2].sequence for c in seen if c[1] == 1]
    assert runs == ["takeoff", "arm", "follow", "climb", "outcome"]
    for run in {c[0] for c in seen}:  # numbered from 1 within each run, the states chained
        steps = [c for c in seen if c[0] == run]
        assert [c[1] for c in steps] == list(range(1, len(steps) + 1))
        assert steps[0][3] == CommandState() and all(a[5] == b[3] for a, b in itertools.pairwise(steps))
        assert all((c[5], c[6]) == command_step(c[2], c[3], c[4]) for c in steps)
    climb = [type(c[6]).__name__ for c in seen if c[2].sequence == "climb"]
    assert climb == ["PlanClimb", "SwapClimb", "MoveClimb", "Await", "Finish"]
    assert [c[6] for c in seen if c[2].sequence == "outcome"][:1] == [Complete("takeoff")]

    def init_failing(self: Any, *a: Any) -> None:
        real(self, *a)
        self.observe = lambda *_call: (_ for _ in ()).throw(RuntimeError("a broken recorder"))

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(Commands, "__init__", init_failing)
        assert replace(world, did=[]).run(Commands) == did
