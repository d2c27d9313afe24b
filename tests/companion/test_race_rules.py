"""A pop-up obstacle's decisions and its race against the braking deadline
(companion.race_rules.race_step), on their own and against the code as it was before they were
a function of their own: a copy of that race (`_old_race`, `_old_brake_at_deadline`, `_OldGuard`)
and today's `Brakes.race` with `StopGuard` run in the same world (a virtual clock; the replan,
its notes, requests for the stop, nearer pop-ups, the flight state, the stop's planning and the
swap scripted) make the same calls in the same order at the same times: stops planned (and
when), waits (how long, on what), cancels, brakes (reason, blocked waypoint, prepared stop),
swaps, Braking transitions and events; and each step today's race took chains and reproduces.
Likewise a copy of `Replans.avoid` (`_old_avoid`) and today's: the same announcements, events,
brakes, races and deadlines brought forward."""

from __future__ import annotations

import asyncio
import contextlib
import logging
import selectors
from dataclasses import dataclass, field, replace
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import companion.braking as braking
from companion.braking import Brakes, Replanned, StopGuard, StopPlan, stop_fields
from companion.config import Config
from companion.flight import HOLDING_CONTROL, State
from companion.race_rules import (
    BRAKE_PREPARE,
    DONE,
    ENDED,
    NONE,
    PLANNING,
    RACING,
    Announce,
    Brake,
    Braked,
    Clear,
    Deadline,
    Forward,
    Forwarded,
    GiveUp,
    PopUp,
    Prepare,
    PreparedSwap,
    Race,
    RaceRules,
    RaceState,
    ReplanCancelled,
    ReplanOver,
    SwapPrepared,
    Tick,
    Wait,
    Won,
    first_state,
    race_step,
    racing,
)
from companion.supervisor import Braking
from planner_core import hold

log = logging.getLogger("companion")
TIMES = st.floats(-2.0, 8.0, allow_nan=False)
RULES = st.builds(RaceRules, st.just("['p']"), st.just("obstacles ['p']"), st.floats(0.05, 1.0),
                  st.sampled_from([2.0 / 50, 2.0 / 30, 2.0 / 100]))
STOPS = st.sampled_from([NONE, PLANNING, DONE])


# -- the rules on their own ----------------------------------------------------------------------


def _seen(data: st.DataObject, s: RaceState) -> Any:
    """Any observation the shells could make in phase `s.phase` (a deadline brought forward
    now and then in any phase of a race)."""
    d = data.draw
    if s.phase == "popup":
        hit = d(st.none() | TIMES)
        return PopUp(d(st.booleans()), 0.0, hit, d(st.floats(0.0, 2.0)))
    assert s.deadline is not None
    if d(st.integers(0, 5)) == 0 or s.phase == ENDED:
        stop = d(STOPS)
        return Forward(s.deadline - d(st.floats(-0.5, 2.0)), d(TIMES), d(st.sampled_from(["", "['q']"])), stop,
                       d(st.none() | TIMES) if stop == DONE else None)
    if s.phase == RACING:
        if d(st.integers(0, 9)) == 0:
            return ReplanOver(d(st.booleans()), "local replan: no", d(st.none() | st.integers(0, 3)), "inside 'q'",
                              d(st.sampled_from(["", "", "RuntimeError('bug')"])))
        stop = d(STOPS)
        held = d(st.sampled_from([True] * 8 + [False]))
        return Tick(held, "STREAMING" if held else "PILOT", stop, d(st.booleans()) if stop == NONE else False,
                    d(st.none() | TIMES) if stop == DONE else None, d(TIMES) if held else None)
    if s.phase == "cancelling":
        return ReplanCancelled(tuple(d(st.lists(st.sampled_from(["local replan: no", "full replan: late"]),
                                                max_size=2))))
    return PreparedSwap(d(st.booleans()), d(st.none() | st.just("no verified stop")))


def _drive(rules: RaceRules, data: st.DataObject) -> list[tuple[RaceState, Any, RaceState, Any]]:
    s, steps = first_state(), []
    for _ in range(400):
        o = _seen(data, s)
        after, action = race_step(rules, s, o)
        steps.append((s, o, after, action))
        s = after
        if s.phase == ENDED and (s.deadline is None or (not isinstance(o, Forward) and data.draw(st.booleans()))):
            return steps  # no race (its pop-up ended it), or the race's end (a nearer pop-up may follow)
    return steps


@settings(max_examples=300, deadline=None)
@given(RULES, st.data())
def test_the_deadline_only_comes_forward_and_every_note_is_said_at_it(rules: RaceRules, data: st.DataObject) -> None:
    """The deadline starts at the hit and only comes earlier (nor the hit later), notes only
    accumulate; a stop planned for a later deadline is dropped; a brake at the deadline says
    every note, in order; a Braked one carries the deadline and hit of that moment."""
    for before, o, after, action in _drive(rules, data):
        assert after.notes[:len(before.notes)] == before.notes
        if isinstance(o, PopUp):
            assert before == first_state()
            raced = o.in_flight and o.hit is not None and o.committed is not None and \
                o.hit >= o.committed + rules.split_ahead
            assert isinstance(action, Race) == raced
            assert after == (racing(o.hit) if raced and o.hit is not None else RaceState(ENDED))
            if isinstance(action, Brake):
                assert action.reason.startswith("obstacle ['p'] is ") and action.reason.endswith("too close to replan")
            assert isinstance(action, Announce) == (not o.in_flight)
            assert isinstance(action, Clear) == (o.in_flight and o.hit is None)
            continue
        assert before.deadline is not None and after.deadline is not None and after.hit is not None
        assert after.deadline <= before.deadline and before.hit is not None and after.hit <= before.hit
        if isinstance(o, Forward):
            assert action == Forwarded(o.deadline < before.deadline, action.cancel)
            assert after.deadline == min(before.deadline, o.deadline)
            if action.cancel:
                assert o.stop != NONE and (o.start is None or o.start > o.deadline)
            if o.deadline < before.deadline and o.names:
                assert after.notes[-1] == f"deadline brought forward by obstacles {o.names} (hit at t={o.hit:.2f} s)"
            else:
                assert after.notes == before.notes
        else:
            assert (after.deadline, after.hit, after.notes) == (before.deadline, before.hit, before.notes)
        if isinstance(action, SwapPrepared):
            assert isinstance(o, ReplanCancelled)
            text = action.reason
            assert text.startswith(f"{rules.what}: no verified replan by the braking deadline t={before.deadline:.2f} s")
            at = [text.index(n) for n in (*o.notes, *before.notes, "the replan is still running")]
            assert at == sorted(at)
        if isinstance(o, PreparedSwap):
            assert (action == Braked(before.reason, before.deadline, before.hit)) == o.swapped
            if not o.swapped:
                assert isinstance(action, Brake) and action.reason.startswith(before.reason + "; the prepared stop")


@settings(max_examples=300, deadline=None)
@given(RULES, st.data())
def test_a_turn_waits_at_most_half_a_spare_and_stops_waiting_only_with_a_stop_under_way(rules: RaceRules,
                                                                                      data: st.DataObject) -> None:
    """Out of control ends the race; a wait is never longer than half the spare nor past the
    stop's start less the spare; the deadline is met only with the stop planning (or planned),
    never before its start less the spare; the replan's end decides alone."""
    for before, o, after, action in _drive(rules, data):
        if isinstance(o, Tick):
            assert before.deadline is not None
            if not o.in_control:
                assert action == GiveUp() and after.phase == ENDED
                continue
            assert o.committed is not None
            start = before.deadline if o.start is None else o.start
            planning = o.stop != NONE or o.asked
            wake = start - rules.spare if planning else min(start - rules.spare, before.deadline - rules.prepare)
            if isinstance(action, Wait):
                assert 0 < action.timeout <= rules.spare / 2 and action.timeout <= wake - o.committed
                assert action.prepare == (o.stop == NONE and o.asked) and action.asked == (not planning)
                assert action.stop == (o.stop == PLANNING or action.prepare)
            elif isinstance(action, Deadline):
                assert planning and wake <= o.committed and action.prepare == (o.stop == NONE and o.asked)
                assert after.phase == "cancelling"
            else:
                assert action == Prepare() and not planning and wake <= o.committed and after == before
        if isinstance(o, ReplanOver):
            assert after.phase == ENDED
            if o.ok and not o.error:
                assert action == Won()
            else:
                assert isinstance(action, Brake) and action.prepared and action.reason.startswith(rules.what + ": ")
                assert action.blocked == (None if o.error else o.blocked)
                assert ("mission waypoint" in action.reason) == (action.blocked is not None)


def test_an_observation_out_of_turn_is_refused() -> None:
    rules = RaceRules("['p']", "obstacles ['p']", 0.15, 0.04)
    with pytest.raises(ValueError, match="Tick observed in phase 'popup'"):
        race_step(rules, first_state(), Tick(True, "STREAMING", NONE, False, None, 1.0))
    s, a = race_step(rules, first_state(), PopUp(True, 1.0, 4.0, 1.1))
    assert a == Race() and s == racing(4.0)
    with pytest.raises(ValueError, match="PreparedSwap observed in phase 'racing'"):
        race_step(rules, s, PreparedSwap(True, None))
    s, a = race_step(rules, s, Forward(2.5, 4.0, "", NONE, None))
    assert a == Forwarded(True) and (s.deadline, s.hit, s.notes) == (2.5, 4.0, ())
    # far from the deadline: wait a tick; near it, the stop is prepared, then the race stops waiting
    s2, a = race_step(rules, s, Tick(True, "STREAMING", NONE, False, None, 1.0))
    assert a == Wait(0.02, False, False, True) and s2 == s
    _, a = race_step(rules, s, Tick(True, "STREAMING", NONE, False, None, 2.5 - BRAKE_PREPARE))
    assert a == Prepare()
    _, a = race_step(rules, s, Tick(True, "STREAMING", PLANNING, False, None, 2.47))
    assert a == Deadline(False)


# -- the race as it was: the oracle -------------------------------------------------------------


class _OldGuard:
    """braking.StopGuard before its deadline was the race's rules' (verbatim)."""

    def __init__(self, base: Any, hit: float) -> None:
        self.base = base
        self._deadline = hit
        self.hit = hit
        self.notes: list[str] = []
        self.future: asyncio.Future[StopPlan] | None = None
        self._asked: asyncio.Future[None] | None = None

    @property
    def deadline(self) -> float:
        return self._deadline

    def bring_forward(self, deadline: float, hit: float, why: str = "") -> None:
        if deadline >= self._deadline:
            return
        self._deadline, self.hit = deadline, min(self.hit, hit)
        if why:
            self.notes.append(why)
        plan = self.ready()
        if self.future is not None and (plan is None or plan.trajectory is None or plan.start > deadline):
            self.future.cancel()  # planned for the later deadline (or still planning for it)
            self.future = None

    def prepare(self) -> None:
        asked = self.asked()
        if not asked.done():
            asked.set_result(None)

    def asked(self) -> asyncio.Future[None]:
        if self._asked is None:
            self._asked = asyncio.get_running_loop().create_future()
        return self._asked

    def planning(self, future: asyncio.Future[StopPlan]) -> None:
        self.future = future
        self._asked = None

    def ready(self) -> StopPlan | None:
        f = self.future
        if f is None or not f.done() or f.cancelled() or f.exception() is not None:
            return None
        return f.result()

    def start_time(self) -> float:
        plan = self.ready()
        return self.deadline if plan is None or plan.trajectory is None else plan.start

    def cancel(self) -> None:
        if self.future is not None:
            self.future.cancel()


async def _old_race(self: Any, guard: Any, replan: Any, notes: list[str], arrived: float, what: str) -> None:
    """Brakes._race before its decisions were companion.race_rules (commit 5ed79a9), verbatim."""
    # Swap with a few periods to spare: the loop may be late, and swap() refuses a split
    # less than half a period ahead.
    spare = 2.0 / self.cfg.setpoints.rate_hz
    flight = self.flight
    while not replan.done():
        if flight.state not in HOLDING_CONTROL:  # e.g. a pilot took over meanwhile
            replan.cancel()
            guard.cancel()
            return
        if guard.future is None and guard.asked().done():
            self._prepare(guard)
        wake = guard.start_time() - spare
        if guard.future is None:
            wake = min(wake, guard.deadline - BRAKE_PREPARE)
        delay = wake - self.control.committed()  # a stop starts after the setpoints already sent
        if delay <= 0:
            if guard.future is None:
                self._prepare(guard)
                continue
            break
        waiting: set[asyncio.Future[Any]] = {replan}
        if guard.future is None:
            waiting.add(guard.asked())  # wake as soon as the stop is asked for
        elif not guard.future.done():
            waiting.add(guard.future)
        # at most a tick at a time: another pop-up may bring the deadline forward
        await asyncio.wait(waiting, timeout=min(delay, spare / 2), return_when=asyncio.FIRST_COMPLETED)
    if replan.done():
        failed = None if replan.cancelled() else replan.exception()
        if failed is not None:
            log.error("replan failed: %r", failed)
        result = Replanned(False, f"replan error: {failed!r}") if failed is not None else replan.result()
        if result.ok:
            guard.cancel()
            return
        why = (f"{what}: mission waypoint {result.blocked} is blocked ({result.blocked_message})"
               if result.blocked is not None else f"{what}: no safe plan ({result.reason})")
        await self.brake(why, arrived, blocked=result.blocked, prepared=guard.ready())
        return
    replan.cancel()
    with contextlib.suppress(asyncio.CancelledError):
        await replan
    pending = "; ".join([*notes, *guard.notes, "the replan is still running"])
    await self._brake_at_deadline(guard, arrived,
                                  f"{what}: no verified replan by the braking deadline t={guard.deadline:.2f} s "
                                  f"(the plan enters the obstacle at t={guard.hit:.2f} s; {pending})")


async def _old_brake_at_deadline(self: Any, guard: Any, arrived: float, reason: str) -> None:
    """Brakes._brake_at_deadline before (verbatim)."""
    plan = await self._prepared(guard)
    swap_time = self.control.now()
    if not self._commit(guard.base, plan, arrived):
        await self.brake(reason + "; the prepared stop was not usable: "
                         + ("none planned" if plan is None else plan.message), arrived)
        return
    assert plan is not None
    self.flight.handle(Braking(reason))
    self.report.event("braking", f"{reason}; braking to a stop and holding", reason=reason, blocked_waypoint=None,
                      detail=plan.message, deadline=round(guard.deadline, 4), hit_time=round(guard.hit, 4),
                      swap_time=round(swap_time, 4), **stop_fields(plan))


class _OldBrakes(Brakes):
    _race = _old_race  # type: ignore[assignment]
    _brake_at_deadline = _old_brake_at_deadline  # type: ignore[assignment]


class _Clock:
    now = 0.0


class _VirtualSelector(selectors.DefaultSelector):
    """Time passes only when the loop would sleep: it jumps to the next timer at once."""

    def __init__(self, clock: _Clock) -> None:
        super().__init__()
        self.clock = clock

    def select(self, timeout: float | None = None) -> Any:
        if timeout is None:
            raise RuntimeError("the world stalled: nothing scheduled and nothing ready")
        self.clock.now += max(0.0, timeout)
        return super().select(0)


@dataclass
class _World:
    """What the race reads and when, each drawn: the same for either race."""

    rate_hz: float
    lead: float
    hit: float
    first_deadline: float
    replan: tuple[float, str] | None  # when it ends, how ("ok", "fail", "blocked", "error"); None: never
    notes: list[tuple[float, str]]  # what the replan notes, when
    asks: list[float]  # when the replan asks for the stop (its local replan failed)
    forwards: list[tuple[float, float, float, str]]  # nearer pop-ups: when, deadline, hit, names
    taken_over: float | None  # when the flight stops holding control
    stops: list[tuple[float, str, float]]  # each stop planned: how long, how ("ok", "none", "error"), start offset
    swaps: list[bool]
    did: list[tuple[Any, ...]] = field(default_factory=list)

    def run(self, old: bool) -> tuple[list[tuple[Any, ...]], list[tuple[Any, ...]], Any]:
        world, clock, did = self, _Clock(), self.did
        steps: list[tuple[Any, ...]] = []
        stops, swaps = list(self.stops), list(self.swaps)
        loop = asyncio.SelectorEventLoop(_VirtualSelector(clock))
        loop.time = lambda: clock.now  # type: ignore[method-assign]
        faults: list[Any] = []
        loop.set_exception_handler(lambda _loop, context: faults.append(context))  # a broken world fails the test

        class Watched(asyncio.Future):  # type: ignore[type-arg]
            def __init__(self, name: str) -> None:
                super().__init__(loop=loop)
                self.name = name

            def cancel(self, msg: Any = None) -> bool:
                did.append(("cancel", self.name, round(clock.now, 9), self.done()))
                return super().cancel(msg)

        base = hold(np.array([0.0, 0.0, -1.5]), 0.0)
        control = SimpleNamespace(committed=lambda: clock.now + world.lead, now=lambda: clock.now, active=base,
                                  swap=lambda _t, start, _a, what: did.append(("swap", start, what, clock.now))
                                  or (swaps.pop(0) if swaps else True))
        flight = SimpleNamespace(state=State.STREAMING,
                                 handle=lambda e: did.append(("handle", type(e).__name__, e.reason)))
        report = SimpleNamespace(event=lambda kind, msg, **kw: did.append(("event", kind, msg, sorted(kw.items()))))
        cfg = Config()
        cfg = replace(cfg, setpoints=replace(cfg.setpoints, rate_hz=self.rate_hz))
        kind = _OldBrakes if old else Brakes
        brakes = kind(cfg, flight, control, SimpleNamespace(loop=loop), report, None,  # type: ignore[arg-type]
                      lambda: np.zeros(3))
        n_stops = [0]

        def stop_future(_base: Any, starts: list[float]) -> Any:
            n_stops[0] += 1
            f = Watched(f"stop {n_stops[0]}")
            did.append(("prepare", tuple(starts), round(clock.now, 9)))
            took, how, offset = stops.pop(0) if stops else (0.02, "ok", 0.0)

            def done() -> None:
                if f.done():
                    return
                if how == "error":
                    f.set_exception(RuntimeError("stop planner bug"))
                else:
                    traj = hold(np.zeros(3), starts[0] + offset) if how == "ok" else None
                    f.set_result(StopPlan(traj, starts[0] + offset, f"stop {how}", True))

            loop.call_at(clock.now + took, done)
            return f

        async def brake(reason: str, _arrived: Any, blocked: int | None = None, prepared: Any = None) -> None:
            did.append(("brake", reason, blocked, None if prepared is None else prepared.start, round(clock.now, 9)))

        brakes.stop_future = stop_future  # type: ignore[method-assign]
        brakes.brake = brake  # type: ignore[method-assign]
        if not old:
            brakes.observe = lambda *call: steps.append(call)
        real_wait = asyncio.wait

        async def wait(fs: Any, timeout: float, return_when: str) -> Any:
            did.append(("wait", round(timeout, 12), sorted(getattr(f, "name", "asked") for f in fs),
                        round(clock.now, 9)))
            return await real_wait(fs, timeout=timeout, return_when=return_when)

        async def main() -> Any:
            replan = Watched("replan")
            notes: list[str] = []
            if old:
                guard: Any = _OldGuard(base, self.hit)
            else:
                guard = StopGuard(base, self.hit)
                guard.steps = brakes.race_steps("['p']")
                guard.steps.state = racing(self.hit)  # as after the pop-up's Race
            guard.bring_forward(self.first_deadline, self.hit)

            def end_replan(how: str) -> None:
                if replan.done():
                    return
                if how == "error":
                    replan.set_exception(RuntimeError("replan bug"))
                else:
                    replan.set_result({"ok": Replanned(True), "fail": Replanned(False, "; ".join(notes) or "no plan"),
                                       "blocked": Replanned(False, "x", 2, "inside 'p'")}[how])

            if self.replan is not None:
                loop.call_at(self.replan[0], end_replan, self.replan[1])
            for t, text in self.notes:
                loop.call_at(t, lambda text=text: None if replan.done() else notes.append(text))
            for t in self.asks:
                loop.call_at(t, guard.prepare)
            for t, deadline, hit, names in self.forwards:
                def forward(deadline: float = deadline, hit: float = hit, names: str = names) -> None:
                    if brakes.race_guard is guard:  # as Replans.avoid: only while the race runs
                        guard.bring_forward(deadline, hit, f"deadline brought forward by obstacles {names} "
                                            f"(hit at t={hit:.2f} s)" if old else names)
                loop.call_at(t, forward)
            if self.taken_over is not None:
                loop.call_at(self.taken_over, lambda: setattr(flight, "state", State.PILOT))
            try:
                await brakes.race(guard, replan, notes, 0.0, "obstacles ['p']")  # type: ignore[arg-type]
                did.append(("ended", round(clock.now, 9)))
            except asyncio.CancelledError:
                did.append(("raised", "CancelledError", round(clock.now, 9)))
            return guard.deadline, guard.hit, list(guard.notes)

        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(braking, "splice", lambda _a, b: b)
            mp.setattr(asyncio, "wait", wait)
            try:
                end = loop.run_until_complete(asyncio.wait_for(main(), 60.0))
            finally:
                loop.close()
        assert not faults, faults
        return did, steps, end


WHEN = st.floats(0.0, 4.0, allow_nan=False)
WORLDS = st.builds(
    _World,
    st.sampled_from([50.0, 30.0, 100.0]),
    st.floats(0.02, 0.1),
    st.floats(0.2, 4.0),
    st.floats(-1.5, 3.0) | st.floats(0.6, 3.0),
    st.none() | st.tuples(st.floats(0.0, 1.0) | WHEN, st.sampled_from(["ok", "ok", "fail", "blocked", "error"])),
    st.lists(st.tuples(WHEN, st.sampled_from(["local replan: no", "full replan: slow"])), max_size=3),
    st.lists(WHEN, max_size=2),
    st.lists(st.tuples(WHEN, st.floats(-1.5, 3.0), st.floats(0.0, 4.0), st.sampled_from(["['n']", "['m']"])),
             max_size=3),
    st.none() | st.floats(0.0, 1.0),
    st.lists(st.tuples(st.floats(0.0, 0.5), st.sampled_from(["ok", "ok", "ok", "none", "error"]),
                       st.floats(0.0, 0.06)), max_size=4),
    st.lists(st.booleans() | st.just(True), max_size=3),
)


@settings(max_examples=300, deadline=None)
@given(WORLDS)
def test_the_rules_do_what_the_race_did(world: _World) -> None:
    """The same stops planned (starts, times), waits (timeout, what on, when), cancels,
    brakes (reason, blocked, prepared start), swaps, Braking transitions and events, in the
    same order, the same end, and the deadline, hit and notes the guard ends with."""
    old_did, _, old_end = replace(world, did=[]).run(old=True)
    new_did, steps, new_end = replace(world, did=[]).run(old=False)
    assert new_did == old_did
    assert (new_end[0], new_end[1], list(new_end[2])) == old_end
    # each step the race took chains to the one before and is the rules' own answer
    assert [s[1] for s in steps] == list(range(1, len(steps) + 1))
    for i, (_race, _step, rules, before, seen, after, action) in enumerate(steps):
        assert race_step(rules, before, seen) == (after, action)
        assert i == 0 or steps[i - 1][5] == before


def test_a_late_replan_brakes_at_the_deadline_with_the_prepared_stop() -> None:
    """One world in words: a replan that never ends, its local replan failing at 0.3 s (the stop
    asked for then), a nearer pop-up at 0.5 s: the stop is planned at 0.3 s for the first deadline,
    dropped at 0.5 s, planned again for the nearer one BRAKE_PREPARE before it (less the lead),
    and swapped in by its deadline."""
    world = _World(50.0, 0.06, 3.0, 1.9, None, [(0.3, "local replan: no")], [0.3], [(0.5, 1.2, 2.2, "['n']")],
                   None, [], [])
    did, steps, (deadline, hit, notes) = world.run(old=False)
    prepared = [d for d in did if d[0] == "prepare"]
    assert prepared == [("prepare", (1.9,), 0.3), ("prepare", (1.2,), pytest.approx(1.2 - BRAKE_PREPARE - 0.06, abs=0.02))]
    assert ("cancel", "stop 1", pytest.approx(0.5, abs=0.02), True) in did
    handled = [d for d in did if d[0] == "handle"]
    assert len(handled) == 1 and "deadline t=1.20 s" in handled[0][2] and "local replan: no" in handled[0][2]
    assert "deadline brought forward by obstacles ['n'] (hit at t=2.20 s)" in handled[0][2]
    assert (deadline, hit, tuple(notes)) == (1.2, 2.2, ("deadline brought forward by obstacles ['n'] (hit at t=2.20 s)",))
    assert [type(s[6]).__name__ for s in steps][-3:] == ["Deadline", "SwapPrepared", "Braked"]


# -- the pop-up's decision as it was: the oracle ----------------------------------------------------


async def _old_avoid(self: Any, new: list[Any], ids: list[str], arrived: float, announce: Any) -> None:
    """Replans.avoid before its decision was companion.race_rules (commit d018ae6), verbatim but
    for the names it reads from this test's world (`AW`)."""
    names = str(ids)
    race = self.brakes.race_guard
    route = self.control.route
    if race is not None and self.control.active is race.base and route is not None and self.control.flying:
        # A replan for an earlier pop-up holds the lock until it is swapped in or its
        # braking deadline: this obstacle may need the stop sooner.
        now = self.control.now()
        hit = AW.first_hit(race.base, now, new, route.mission.radius)
        if hit is not None:
            race.bring_forward(AW.brake_deadline(race.base, now, hit, route.mission.bounds), hit,
                               f"deadline brought forward by obstacles {names} (hit at t={hit:.2f} s)")
    async with self.lock:
        route = self.control.route
        if not self.in_flight() or route is None:
            announce()
            return
        active = self.control.active
        assert active is not None
        now = self.control.now()
        radius, split_ahead = route.mission.radius, self.cfg.planner.split_ahead
        hit = AW.first_hit(active, now, new, radius)
        if hit is None:
            announce()
            self.report.event("obstacles_clear", f"obstacles {names}: the current trajectory stays clear; no replan",
                              obstacles=ids)
            return
        if hit < self.control.committed() + split_ahead:  # setpoints up to now + lead are sent
            announce()
            await self.brakes.brake(f"obstacle {names} is {hit - now:.2f} s ahead: too close to replan", arrived)
            return
        await self._avoid_race(new, names, arrived, hit, announce)


AW = SimpleNamespace(first_hit=None, brake_deadline=None)


@dataclass
class _PopUpWorld:
    """What Replans.avoid reads, each drawn: the flight state, whether a route is flown and the
    vehicle flies, a race under way (on the flown plan or an older one), where each plan is hit
    (None: never), the times read, the split's lead."""

    state: State
    route: bool
    flying: bool
    race: int  # 0: none, 1: on the flown plan, 2: on another
    hits: list[float | None]  # first_hit's answers, in order
    now: float
    lead: float
    split_ahead: float

    def run(self, old: bool) -> list[tuple[Any, ...]]:
        import companion.replans as replans

        did: list[tuple[Any, ...]] = []
        hits, world = list(self.hits), self
        active = object()
        guard = None if self.race == 0 else SimpleNamespace(
            base=active if self.race == 1 else object(),
            bring_forward=lambda deadline, hit, said: did.append(
                ("forward", deadline, hit, said if old else f"deadline brought forward by obstacles {said} "
                 f"(hit at t={hit:.2f} s)")))
        route = SimpleNamespace(mission=SimpleNamespace(radius=0.3, bounds="bounds")) if self.route else None
        control = SimpleNamespace(route=route, active=active, flying=self.flying, now=lambda: world.now,
                                  committed=lambda: world.now + world.lead)

        async def brake(reason: str, arrived: float) -> None:
            did.append(("brake", reason, arrived))

        brakes = SimpleNamespace(race_guard=guard, brake=brake)
        if not old:
            rules_cfg = replace(Config().planner, split_ahead=self.split_ahead)
            brakes.race_steps = lambda names: braking.race_run(
                RaceRules(names, f"obstacles {names}", rules_cfg.split_ahead, 0.04), 1,
                lambda *call: did.append(("step", type(call[4]).__name__, type(call[6]).__name__)))
        cfg = replace(Config(), planner=replace(Config().planner, split_ahead=self.split_ahead))
        report = SimpleNamespace(event=lambda kind, msg, **kw: did.append(("event", kind, msg, sorted(kw.items()))))
        flight = SimpleNamespace(state=self.state)

        def first_hit(_traj: Any, now: float, _new: Any, radius: float) -> float | None:
            did.append(("first_hit", now, radius))
            return hits.pop(0) if hits else None

        async def avoid_race(_new: Any, names: str, arrived: float, hit: float, _announce: Any, *_steps: Any) -> None:
            did.append(("race", names, arrived, hit))

        async def main() -> None:
            r = replans.Replans(cfg, flight, control, None, report, asyncio.Lock(), None, None, None,  # type: ignore[arg-type]
                                brakes, None)
            r._avoid_race = avoid_race  # type: ignore[method-assign]
            announce = lambda: did.append(("announce",))  # noqa: E731
            if old:
                await _old_avoid(r, ["polytope"], ["p1", "p2"], 7.5, announce)
            else:
                await r.avoid(["polytope"], ["p1", "p2"], 7.5, announce)  # type: ignore[list-item]

        AW.first_hit, AW.brake_deadline = first_hit, lambda _b, now, hit, bounds: hit - 1.1 - now * 0.0
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(replans, "first_hit", first_hit)
            mp.setattr(replans, "brake_deadline", AW.brake_deadline)
            asyncio.run(main())
        return did


POPUP_WORLDS = st.builds(
    _PopUpWorld,
    st.sampled_from([State.STREAMING, State.STREAMING, State.HOLDING, State.BRAKING]),
    st.booleans() | st.just(True), st.booleans() | st.just(True),
    st.sampled_from([0, 0, 1, 2]),
    st.lists(st.none() | st.floats(0.0, 6.0), min_size=2, max_size=2),
    st.floats(0.0, 5.0), st.floats(0.0, 0.1), st.floats(0.05, 1.0),
)


@settings(max_examples=300, deadline=None)
@given(POPUP_WORLDS)
def test_the_pop_up_decides_what_avoid_did(world: _PopUpWorld) -> None:
    """The same announcements, events, brakes (reason), races (hit), deadlines brought forward
    (deadline, hit, note) and hits asked for, in the same order; each decision a step."""
    old = world.run(old=True)
    new = world.run(old=False)
    assert [d for d in new if d[0] != "step"] == old  # (drawn: ~60 % announce only, 20 % clear, 15 % brake, 8 % race)
    kinds = {d[0] for d in old}
    decided = "Race" if "race" in kinds else "Brake" if "brake" in kinds else "Clear" if "event" in kinds else "Announce"
    assert [d for d in new if d[0] == "step"] == [("step", "PopUp", decided)]
