"""The split-and-swap loop's decisions, as one pure function.

`split_step(rules, state, observation) -> (state, action)` decides, for one plan made in flight,
what `SplitSwap.at_split` (companion/split_swap.py) does next: where to split (what is committed
plus `ahead`), whether that is too close to the obstacle, what a refused plan, a fleet that lost
or whose clock is off, a flown plan that changed while planning, and a refused swap each lead
to, and, when the plan came after its split: the same plan moved later from a hold, or planned
again further ahead (`ahead` from RETRY_MARGIN x the time it took, capped at MAX_AHEAD); at most
twice late and twice changed; the texts said, in order, and the final reason. No I/O, no clock,
no asyncio: the loop observes (the time committed, whether still in control, the plan's outcome
and how long it took, the fleet's answer, the swap's refusal, whether the flown plan holds still),
calls this, shows the call to the flight recorder (/navigator/split) and carries out the action.
`python -m companion replay` runs each recorded call again (companion/replay_split.py).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from companion.control import SWAP_LATE
from companion.plan_budget import MAX_AHEAD, RETRY_MARGIN

FLEET_TRIES = 8  # candidates that lost to other vehicles before a plan is given up (docs/fleet.md)
TOO_CLOSE = "too close to the obstacle to replan"
CHANGED = "the flown plan changed while planning (a stop or another change came first)"
# what each state waits for next (SplitState.expect)
ATTEMPT, PLANNED, COMMITTED, SWAPPED, HELD, MOVED, ENDED = (
    "attempt", "planned", "committed", "swapped", "held", "moved", "ended")


@dataclass(frozen=True)
class SplitRules:
    """One `at_split` call's givens: the split's lead asked for (`[planner] split_ahead`, or the
    caller's), whether a fleet commits the plan and its wait (the fleet's `wait`: 0 without),
    when the flown plan would hit an obstacle (None: no obstacle), and the limits."""

    ahead: float
    fleet: bool = False
    wait: float = 0.0
    hit: float | None = None
    fleet_tries: int = FLEET_TRIES
    retry_margin: float = RETRY_MARGIN
    max_ahead: float = MAX_AHEAD


@dataclass(frozen=True)
class SplitState:
    """What the loop remembers: the lead of the next split, the causes counted, the last reason,
    the texts said (each once, in order), what it waits for next, and this attempt's split, the
    time its plan took and the later split a plan from a hold is moved to."""

    ahead: float
    late: int = 0
    changed: int = 0
    lost: int = 0
    reason: str = ""
    said: tuple[str, ...] = ()
    expect: str = ATTEMPT
    t_split: float | None = None
    took: float | None = None
    t_later: float | None = None


def first_state(rules: SplitRules) -> SplitState:
    """The state a call starts in (a plan is proposed to the fleet, then committed `wait` later:
    companion.commit)."""
    return SplitState(rules.ahead + rules.wait if rules.fleet else rules.ahead)


# -- observations -----------------------------------------------------------------------------


@dataclass(frozen=True)
class Attempt:
    """Before each plan: a plan and its time base are set and the flight is ours (`in_control`;
    else `flight`: the flight state's name), and the trajectory time committed (None: not flying)."""

    in_control: bool
    flight: str
    committed: float | None


@dataclass(frozen=True)
class Planned:
    """The plan's outcome (`ok`: with a route, else its `message`), the seconds it `took`, and,
    then: whether the plan it was spliced on is still flown (`base_flown`), and whether the flown
    plan or its route changed."""

    ok: bool
    message: str
    took: float
    base_flown: bool
    changed: bool


@dataclass(frozen=True)
class Committed:
    """The fleet's answer: None (it may be flown) or why it lost; whether the fleet's clock is
    off; and whether the flown plan changed while it waited."""

    why: str | None
    clock_off: bool
    changed: bool


@dataclass(frozen=True)
class SwapDecided:
    """Control.swap's refusal ("" swapped in), and the trajectory time committed right after."""

    refusal: str
    committed: float | None


@dataclass(frozen=True)
class Held:
    """Whether the flown plan holds still from the split to the later one (planner_core.held_still)."""

    still: bool


@dataclass(frozen=True)
class Moved:
    """Control.swap's refusal of the plan moved to the later split ("" swapped in)."""

    refusal: str


Observation = Attempt | Planned | Committed | SwapDecided | Held | Moved


# -- actions -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class PlanAt:
    """Plan from the flown plan at `t_split`."""

    t_split: float


@dataclass(frozen=True)
class Commit:
    """Propose the plan to the fleet and wait for its commit."""


@dataclass(frozen=True)
class TrySwap:
    """Swap the plan in at `t_split`; refused, `cancel` the fleet's candidate."""

    t_split: float
    cancel: bool


@dataclass(frozen=True)
class CheckHeld:
    """Is the flown plan held still from `t_split` to `t_later`?"""

    t_split: float
    t_later: float


@dataclass(frozen=True)
class MoveLater:
    """Swap the same plan in, moved from `t_split` to `t_later`."""

    t_split: float
    t_later: float


@dataclass(frozen=True)
class Again:
    """Plan again (observe the next Attempt): first `cancel` the fleet's candidate, and report
    the fleet `event` (when not "")."""

    cancel: bool = False
    event: str = ""


@dataclass(frozen=True)
class Done:
    """Swapped in at `t_split` (`moved`: the plan moved there from its own split)."""

    t_split: float
    moved: bool = False


@dataclass(frozen=True)
class Refused:
    """The plan was refused: it ends with the outcome and its message."""

    reason: str


@dataclass(frozen=True)
class GiveUp:
    """No plan is swapped in, for `reason` (first `cancel` the fleet's candidate)."""

    reason: str
    cancel: bool = False


Action = PlanAt | Commit | TrySwap | CheckHeld | MoveLater | Again | Done | Refused | GiveUp
Step = tuple[SplitState, Action]


def _said(s: SplitState, text: str) -> tuple[str, ...]:
    return s.said if text in s.said else (*s.said, text)


def _next(s: SplitState, cancel: bool = False, event: str = "") -> Step:
    """The loop goes on while under 2 late and 2 changed attempts; then ends with the last reason."""
    if s.late < 2 and s.changed < 2:
        return replace(s, expect=ATTEMPT), Again(cancel, event)
    return replace(s, expect=ENDED), GiveUp(s.reason or "too close", cancel)


def _late(rules: SplitRules, s: SplitState) -> Step:
    """The plan came after its split, and was not moved: planned again once, further ahead."""
    assert s.took is not None
    late = s.late + 1
    reason = (f"planning took {s.took:.2f} s, more than the {s.ahead:.2f} s to its split time"
              + (" twice: the computer is too busy to plan this in flight now" if late == 2 else ""))
    if late < 2:
        s = replace(s, said=_said(s, reason + "; planned again once, further ahead"),
                    ahead=min(max(2.0 * s.ahead, rules.retry_margin * s.took + 0.1), rules.max_ahead))
    else:
        s = replace(s, said=_said(s, reason))
    return _next(replace(s, late=late, reason=reason))


def _planned(rules: SplitRules, s: SplitState, changed: bool) -> Step:
    """The plan may be swapped in unless the flown plan changed meanwhile."""
    if changed:
        s = replace(s, changed=s.changed + 1, reason=CHANGED, said=_said(s, CHANGED + "; planning again"))
        return _next(s, cancel=rules.fleet)
    assert s.t_split is not None
    return replace(s, expect=SWAPPED), TrySwap(s.t_split, rules.fleet)


def _ended(s: SplitState, reason: str) -> Step:
    return replace(s, expect=ENDED, reason=reason, said=_said(s, reason)), GiveUp(reason)


def split_step(rules: SplitRules, s: SplitState, o: Observation) -> Step:
    """The new state and what to do next, for observation `o` (the one `s.expect` names)."""
    if s.expect != _EXPECTS[type(o)]:
        raise ValueError(f"{type(o).__name__} observed while waiting for {s.expect!r}")
    if isinstance(o, Attempt):
        if not o.in_control:
            return replace(s, expect=ENDED), GiveUp(f"no longer in control ({o.flight})")
        assert o.committed is not None
        t_split = o.committed + s.ahead  # setpoints up to now + lead are sent
        if rules.hit is not None and t_split >= rules.hit:
            return _ended(s, TOO_CLOSE)
        return replace(s, expect=PLANNED, t_split=t_split, took=None, t_later=None), PlanAt(t_split)
    if isinstance(o, Planned):
        s = replace(s, took=o.took)
        if not o.ok:
            return replace(s, expect=ENDED), Refused(o.message)
        if rules.fleet and o.base_flown:
            return replace(s, expect=COMMITTED), Commit()
        return _planned(rules, s, o.changed)
    if isinstance(o, Committed):
        if o.why is not None and o.clock_off:
            return _ended(s, o.why)  # planning again would not help
        if o.why is not None:
            lost = s.lost + 1
            s = replace(s, lost=lost, reason=o.why,
                        said=_said(s, o.why + ("; planning again against it" if lost < rules.fleet_tries else "")))
            if lost >= rules.fleet_tries:
                return replace(s, expect=ENDED), GiveUp(o.why)
            return replace(s, expect=ATTEMPT), Again(event=f"deconfliction: {o.why}; planning again against it")
        return _planned(rules, s, o.changed)
    if isinstance(o, SwapDecided):
        assert s.t_split is not None and s.took is not None
        if o.refusal == "":
            return replace(s, expect=ENDED), Done(s.t_split)
        if o.refusal != SWAP_LATE:
            return _ended(s, o.refusal)  # an internal check: planning again would not help
        # late, from a hold: the same plan starts later just as well (the curve and its checks
        # do not depend on the time; a fleet's separation does): moved, not planned again
        assert o.committed is not None
        t_later = o.committed + min(max(2.0 * s.ahead, rules.retry_margin * s.took + 0.1), rules.max_ahead)
        if rules.fleet:
            return _late(rules, s)
        return replace(s, expect=HELD, t_later=t_later), CheckHeld(s.t_split, t_later)
    assert s.t_split is not None and s.t_later is not None
    if isinstance(o, Held):
        if o.still:
            return replace(s, expect=MOVED), MoveLater(s.t_split, s.t_later)
        return _late(rules, s)
    if o.refusal == "":
        return replace(s, expect=ENDED), Done(s.t_later, moved=True)
    return _late(rules, s)


_EXPECTS: dict[type, str] = {Attempt: ATTEMPT, Planned: PLANNED, Committed: COMMITTED, SwapDecided: SWAPPED,
                             Held: HELD, Moved: MOVED}
