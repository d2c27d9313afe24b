"""The split-and-swap loop's decisions (companion.split_rules.split_step), on their own and
against the loop as it was before they were a function of their own: a copy of that loop
(`_old_at_split`) and today's `SplitSwap.at_split` run on the same world (the same times
committed, plans, fleet answers, refusals, holds) say the same texts in the same order, end
with the same reason and split, and do the same things (plans asked for, fleet commits and
cancels, swaps, events) in the same order."""

from __future__ import annotations

import asyncio
import math
from dataclasses import dataclass, field, replace
from types import SimpleNamespace
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import companion.split_swap as swapmod
from companion.config import Config
from companion.control import SWAP_DIFFERS, SWAP_JETS, SWAP_LATE
from companion.plan_budget import MAX_AHEAD, RETRY_MARGIN
from companion.route import Outcome
from companion.split_rules import (
    FLEET_TRIES,
    Again,
    Attempt,
    CheckHeld,
    Committed,
    Done,
    GiveUp,
    Held,
    Moved,
    MoveLater,
    PlanAt,
    Planned,
    Refused,
    SplitRules,
    SplitState,
    SwapDecided,
    TrySwap,
    first_state,
    split_step,
)

REFUSALS = st.sampled_from(["", SWAP_LATE, SWAP_LATE, SWAP_DIFFERS, SWAP_JETS])
TIMES = st.floats(0.0, 100.0, allow_nan=False)
TOOK = st.floats(0.0, 1.0, allow_nan=False) | st.floats(0.0, 40.0, allow_nan=False)
MOSTLY = st.sampled_from([True, True, True, False])


def _observation(data: st.DataObject, s: SplitState) -> Any:
    """Any observation the loop could make where the rules wait for `s.expect`."""
    d = data.draw
    if s.expect == "attempt":
        return Attempt(d(MOSTLY), "STREAMING", d(TIMES))
    if s.expect == "planned":
        return Planned(d(MOSTLY), "refused by the planner", d(TOOK), d(st.booleans()), d(st.booleans()))
    if s.expect == "committed":
        why = d(st.sampled_from([None, None, "mission m: lost to v2"]))
        return Committed(why, d(st.booleans()), d(st.booleans()))
    if s.expect == "swapped":
        return SwapDecided(d(REFUSALS), d(TIMES))
    if s.expect == "held":
        return Held(d(st.booleans()))
    return Moved(d(st.sampled_from(["", SWAP_LATE])))


RULES = st.builds(SplitRules, st.floats(0.01, 5.0), st.booleans(), st.floats(0.0, 0.5),
                  st.one_of(st.none(), st.floats(0.0, 120.0)))


def _drive(rules: SplitRules, data: st.DataObject) -> list[tuple[SplitState, Any, SplitState, Any]]:
    """One call of the loop, the world drawn: every step (before, observation, after, action)."""
    s, steps = first_state(rules), []
    for _ in range(200):
        o = _observation(data, s)
        after, action = split_step(rules, s, o)
        steps.append((s, o, after, action))
        s = after
        if isinstance(action, Done | GiveUp | Refused):
            return steps
    raise AssertionError("the loop did not end in 200 steps")


@settings(max_examples=300, deadline=None)
@given(RULES, st.data())
def test_every_call_ends_within_its_limits(rules: SplitRules, data: st.DataObject) -> None:
    """Never more than 2 late or 2 changed attempts, nor FLEET_TRIES lost; a plan is asked for
    only at what is committed plus the lead, which starts at the rules' and grows only after a
    late plan: doubled, or RETRY_MARGIN times what it took, capped at MAX_AHEAD; said texts once each."""
    steps = _drive(rules, data)
    plans = [a for _b, _o, _a, a in steps if isinstance(a, PlanAt)]
    end = steps[-1][2]
    assert end.late <= 2 and end.changed <= 2 and end.lost <= FLEET_TRIES
    assert len(plans) <= 3 + FLEET_TRIES and len(set(end.said)) == len(end.said)
    assert first_state(rules).ahead == (rules.ahead + rules.wait if rules.fleet else rules.ahead)
    for before, o, after, action in steps:
        assert after.said[:len(before.said)] == before.said  # said once, in order, never unsaid
        if isinstance(action, PlanAt):
            assert isinstance(o, Attempt) and o.committed is not None and action.t_split == o.committed + before.ahead
            assert rules.hit is None or action.t_split < rules.hit
        if after.ahead != before.ahead:
            assert after.late == before.late + 1 == 1 and before.took is not None
            assert after.ahead == min(max(2.0 * before.ahead, RETRY_MARGIN * before.took + 0.1), MAX_AHEAD)
            assert after.ahead <= MAX_AHEAD
            assert after.said[-1].endswith("; planned again once, further ahead")
        if after.late == 2 > before.late:
            assert "twice" in after.reason and isinstance(action, GiveUp) and action.reason == after.reason


@settings(max_examples=300, deadline=None)
@given(RULES, st.data())
def test_a_refusal_that_is_not_late_ends_at_once_and_moving_later_needs_a_hold(rules: SplitRules,
                                                                              data: st.DataObject) -> None:
    for before, o, after, action in _drive(rules, data):
        if isinstance(o, SwapDecided) and o.refusal not in ("", SWAP_LATE):
            assert action == GiveUp(o.refusal) and after.reason == o.refusal and after.said[-1:] == (o.refusal,)
        if isinstance(action, CheckHeld):
            assert not rules.fleet and isinstance(o, SwapDecided) and o.refusal == SWAP_LATE
        if isinstance(action, MoveLater):
            assert not rules.fleet and o == Held(True) and action == MoveLater(before.t_split, before.t_later)
        if isinstance(action, Done) and action.moved:
            assert not rules.fleet and o == Moved("")
        if isinstance(o, Planned) and not o.ok:
            assert action == Refused(o.message)


def test_a_late_plan_then_a_late_one_again_gives_up_with_both_said() -> None:
    rules = SplitRules(0.15)
    s = first_state(rules)
    s, a = split_step(rules, s, Attempt(True, "", 10.0))
    assert a == PlanAt(10.15)
    s, a = split_step(rules, s, Planned(True, "", 0.7, True, False))
    assert a == TrySwap(10.15, False)
    s, a = split_step(rules, s, SwapDecided(SWAP_LATE, 10.9))
    assert a == CheckHeld(10.15, 10.9 + RETRY_MARGIN * 0.7 + 0.1)
    s, a = split_step(rules, s, Held(False))
    assert a == Again() and s.ahead == RETRY_MARGIN * 0.7 + 0.1
    assert s.said == ("planning took 0.70 s, more than the 0.15 s to its split time; planned again once, further ahead",)
    with pytest.raises(ValueError, match="waiting for 'attempt'"):
        split_step(rules, s, Held(True))


# -- the loop as it was: the oracle ------------------------------------------------------------


async def _old_at_split(self: Any, what: str, arrived: float | None, plan_at: Any, hit: float | None = None,
                        notes: list[str] | None = None, ahead: float | None = None) -> swapmod.Swapped:
    """SplitSwap.at_split before its decisions were companion.split_rules (commit a199b21),
    verbatim but for the names it reads from this test's world (`W`)."""
    messages = notes if notes is not None else []

    def say(text: str) -> None:
        if text not in messages:
            messages.append(text)

    fleet = self.fleet if swapmod.fleet_on(self.fleet) else None
    ahead = self.cfg.planner.split_ahead if ahead is None else ahead
    if fleet is not None:
        ahead += fleet.wait
    late = changed = lost = 0
    reason = ""
    while late < 2 and changed < 2:
        if not self.control.flying or not self.flight.flying_ours:
            return swapmod.Swapped(None, reason=f"no longer in control ({self.flight.state.value})")
        base, route = self.control.active, self.control.route
        assert base is not None
        t_split = self.control.committed() + ahead
        if hit is not None and t_split >= hit:
            reason = "too close to the obstacle to replan"
            say(reason)
            break
        t0 = W.time.monotonic()
        outcome = await plan_at(base, t_split)
        took = W.time.monotonic() - t0
        if not outcome.ok or outcome.route is None:
            return swapmod.Swapped(outcome, t_split, outcome.message)
        if fleet is not None and self.control.active is base:
            why = await fleet.commit(W.splice(base, outcome.route.trajectory), what)
            if why is not None and fleet.clock_off is not None:
                reason = why
                say(why)
                break
            if why is not None:
                lost += 1
                reason = why
                say(why + ("; planning again against it" if lost < FLEET_TRIES else ""))
                if lost >= FLEET_TRIES:
                    break
                self.report.event("fleet", f"deconfliction: {why}; planning again against it", what=what)
                continue
        if self.control.active is not base or self.control.route is not route:
            if fleet is not None:
                fleet.cancel()
            changed += 1
            reason = "the flown plan changed while planning (a stop or another change came first)"
            say(reason + "; planning again")
            continue
        if self.control.swap(W.splice(base, outcome.route.trajectory), t_split, arrived, what, outcome.route):
            return swapmod.Swapped(outcome, t_split)
        if fleet is not None:
            fleet.cancel()
        if self.control.refusal != SWAP_LATE:
            reason = self.control.refusal
            say(reason)
            break
        t_later = self.control.committed() + min(max(2.0 * ahead, RETRY_MARGIN * took + 0.1), MAX_AHEAD)
        if fleet is None and W.held_still(base, t_split, t_later):
            later = outcome.route.shifted(t_later - t_split)
            if self.control.swap(W.splice(base, later.trajectory), t_later, arrived, what, later):
                return swapmod.Swapped(replace(outcome, route=later), t_later)
        late += 1
        reason = (f"planning took {took:.2f} s, more than the {ahead:.2f} s to its split time"
                  + (" twice: the computer is too busy to plan this in flight now" if late == 2 else ""))
        if late < 2:
            say(reason + "; planned again once, further ahead")
            ahead = min(max(2.0 * ahead, RETRY_MARGIN * took + 0.1), MAX_AHEAD)
        else:
            say(reason)
    return swapmod.Swapped(None, reason=reason or "too close")


W = SimpleNamespace(time=None, splice=None, held_still=None)


@dataclass
class _World:
    """What the loop reads, each value drawn: consumed in order, the same for either loop."""

    ours: list[bool]  # flight.flying_ours at each look
    committed: list[float]  # increments of the time committed at each look
    plans: list[tuple[bool, float, int]]  # (ok, took, what changes while planning: 0 nothing, 1 the plan, 2 route)
    answers: list[tuple[str | None, bool, bool]]  # the fleet's (why, clock off, the plan changed while waiting)
    refusals: list[str]
    holds: list[bool]
    fleet: bool
    wait: float
    hit: float | None
    ahead: float | None
    did: list[tuple[Any, ...]] = field(default_factory=list)
    now: float = 0.0
    t: float = 0.0

    def run(self, loop: Any) -> tuple[Any, list[str], list[tuple[Any, ...]]]:
        world = self
        ours, committed, plans = list(self.ours), list(self.committed), list(self.plans)
        answers, refusals, holds = list(self.answers), list(self.refusals), list(self.holds)

        class Control:
            active: Any = object()
            route: Any = object()
            flying = True
            refusal = ""

            def committed(self) -> float:
                world.t += committed.pop(0) if committed else 0.01
                return world.t

            def swap(self, _new: Any, t_split: float, _arrived: Any, what: str, route: Any) -> bool:
                self.refusal = refusals.pop(0) if refusals else ""
                world.did.append(("swap", t_split, what, getattr(route, "dt", None)))
                return not self.refusal

        class Flight:
            state = SimpleNamespace(value="HOLDING")

            @property
            def flying_ours(self) -> bool:
                return ours.pop(0) if ours else True

        control, flight = Control(), Flight()

        class Fleet:
            enabled = True
            wait = self.wait
            clock_off: str | None = None

            async def commit(self, _candidate: Any, what: str) -> str | None:
                why, off, change = answers.pop(0) if answers else (None, False, False)
                self.clock_off = "the fleet clock is off" if off else None
                if change:
                    control.active = object()
                world.did.append(("commit", what))
                return why

            def cancel(self) -> None:
                world.did.append(("cancel",))

        report = SimpleNamespace(event=lambda *a, **kw: world.did.append(("event", *a, *kw.items())))

        async def plan_at(_base: Any, t_split: float) -> Outcome:
            ok, took, change = plans.pop(0) if plans else (True, 0.01, 0)
            world.now += took
            world.did.append(("plan", t_split))
            if change == 1:
                control.active = object()
            elif change == 2:
                control.route = object()
            route = SimpleNamespace(trajectory=None, shifted=lambda dt: SimpleNamespace(trajectory=None, dt=dt))
            return Outcome(ok, message="" if ok else "no plan", route=route)  # type: ignore[arg-type]

        def held(_base: Any, t_split: float, t_later: float) -> bool:
            world.did.append(("held", t_split, t_later))
            return holds.pop(0) if holds else False

        clock = SimpleNamespace(monotonic=lambda: world.now)
        fleet = Fleet() if self.fleet else None
        split = swapmod.SplitSwap(Config(), flight, control, report, fleet)  # type: ignore[arg-type]
        notes: list[str] = ["earlier note"]
        W.time, W.splice, W.held_still = clock, (lambda _a, b: b), held
        with pytest.MonkeyPatch.context() as mp:
            mp.setattr(swapmod, "time", clock)
            mp.setattr(swapmod, "splice", lambda _a, b: b)
            mp.setattr(swapmod, "held_still", held)
            done = asyncio.run(loop(split, "mission m", None, plan_at, hit=self.hit, notes=notes, ahead=self.ahead))
        return done, notes, self.did


WORLDS = st.builds(
    _World,
    st.lists(MOSTLY, max_size=12),
    st.lists(st.floats(0.0, 3.0, allow_nan=False), max_size=30),
    st.lists(st.tuples(st.booleans() | st.just(True), TOOK, st.sampled_from([0, 0, 0, 1, 2])), max_size=14),
    st.lists(st.tuples(st.sampled_from([None, None, "mission m: lost to v2"]), st.booleans(), st.booleans()),
             max_size=14),
    st.lists(REFUSALS, max_size=14),
    st.lists(st.booleans(), max_size=6),
    st.booleans(), st.floats(0.0, 0.5),
    st.one_of(st.none(), st.floats(0.0, 200.0)),
    st.one_of(st.none(), st.floats(0.01, 5.0)),
)


@settings(max_examples=400, deadline=None)
@given(WORLDS)
def test_the_rules_do_what_the_loop_did(world: _World) -> None:
    """The same texts in the same order (after what was noted before), the same reason, split
    and plan (moved or not), and the same plans, commits, cancels, swaps and events in order."""
    was = replace(world, did=[])
    old, old_notes, old_did = was.run(_old_at_split)
    now = replace(world, did=[])
    new, new_notes, new_did = now.run(swapmod.SplitSwap.at_split)
    assert new_notes == old_notes and new_did == old_did
    assert (new.ok, new.reason, new.outcome is None) == (old.ok, old.reason, old.outcome is None)
    assert new.t_split == old.t_split or (math.isnan(new.t_split) and math.isnan(old.t_split))
    if new.outcome is not None and old.outcome is not None:
        assert getattr(new.outcome.route, "dt", None) == getattr(old.outcome.route, "dt", None)


def test_each_step_is_shown_with_its_call_and_number() -> None:
    """The observer sees every step of a call, numbered from 1, and an observer that fails
    changes nothing of what the loop does."""
    world = _World([], [1.0], [(True, 0.5, 0)], [], [SWAP_LATE], [True], False, 0.0, None, 0.15)
    seen: list[tuple[Any, ...]] = []
    real = swapmod.SplitSwap.__init__

    def init(self: Any, *a: Any) -> None:
        real(self, *a)
        self.observe = lambda *call: seen.append(call)

    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(swapmod.SplitSwap, "__init__", init)
        done, notes, _did = world.run(swapmod.SplitSwap.at_split)
    assert done.ok and notes == ["earlier note"]
    assert [(c[0], c[1]) for c in seen] == [(1, i) for i in range(1, 6)]
    assert [type(c[7]) for c in seen] == [PlanAt, TrySwap, CheckHeld, MoveLater, Done]
    assert all(c[6] == split_step(c[3], c[4], c[5])[0] for c in seen)

    def fails(*_call: Any) -> None:
        raise RuntimeError("a broken recorder")

    def init_failing(self: Any, *a: Any) -> None:
        real(self, *a)
        self.observe = fails

    world2 = replace(world, did=[], t=0.0, now=0.0)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(swapmod.SplitSwap, "__init__", init_failing)
        done2, _n, did2 = world2.run(swapmod.SplitSwap.at_split)
    assert done2.ok and done2.t_split == done.t_split and did2 == world.did
