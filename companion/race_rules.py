"""The pop-up obstacle's decisions and its race against the braking deadline, as one pure function.

`race_step(rules, state, observation) -> (state, action)` decides, for one pop-up obstacle
taken in while flying (companion/replans.py `Replans.avoid`) and the race that may follow
(companion/braking.py `Brakes.race`):
- at the pop-up: announce only (no mission flown), no replan (the flown plan stays clear), brake
  now (it would be hit before the split a replan needs), or race a replan against the braking
  deadline, which starts at the hit;
- the deadline brought forward (`StopGuard.bring_forward`, its one writer: the race's own first
  estimate, and any nearer pop-up during the race), and whether the stop planned (or planning)
  for the later deadline is dropped;
- each turn of the race while the replan is out: give up (the pilot took over), plan the stop
  now, wait (how long, and for what), or stop waiting at the deadline;
- the end: the replan swapped in, a brake because it failed (its reason, the blocked waypoint),
  or at the deadline the prepared stop (the reason, with every note said), else a stop planned
  then.
No I/O, no clock, no asyncio: the shells observe (where the flown plan would hit, the time
committed, whether the stop is asked for, planning or ready and where it starts, the replan's
outcome), call this, show the call to the flight recorder (/brakes/race) and carry out the action.
`python -m companion replay` runs each recorded call again (companion/replay_race.py).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

# Start preparing the stop this long before the braking deadline if the replan is still out.
BRAKE_PREPARE = 0.35
# what the state waits for next (RaceState.phase); a deadline may be brought forward in any but
# the first
POPUP, RACING, CANCELLING, SWAPPING, ENDED = "popup", "racing", "cancelling", "swapping", "ended"
# the stop for the deadline (what the shells observe of StopGuard.future)
NONE, PLANNING, DONE = "none", "planning", "done"


@dataclass(frozen=True)
class RaceRules:
    """One pop-up's givens: its obstacles' ids as said (`names`), what races (`what`), the
    split a replan needs ([planner] split_ahead), the time to spare before the stop's start
    (two setpoint periods: the loop may be late, and a swap less than half a period ahead is
    refused) and how long before the deadline the stop is prepared."""

    names: str
    what: str
    split_ahead: float
    spare: float
    prepare: float = BRAKE_PREPARE


@dataclass(frozen=True)
class RaceState:
    """What the race remembers: what it waits for next, the braking deadline (the latest start
    of the stop) and the hit it is for, the notes said when it was brought forward, and the
    reason of a brake at the deadline."""

    phase: str = POPUP
    deadline: float | None = None
    hit: float | None = None
    notes: tuple[str, ...] = ()
    reason: str = ""


def first_state() -> RaceState:
    return RaceState()


def racing(hit: float) -> RaceState:
    """The state a race starts in: the deadline at the hit (no stop may start later)."""
    return RaceState(RACING, hit, hit)


# -- observations -----------------------------------------------------------------------------


@dataclass(frozen=True)
class PopUp:
    """At the pop-up, under the navigator's lock: whether a mission is flown under our control
    (`in_flight`), then the trajectory time now, where the flown plan first enters the new
    obstacles (None: never), and the time committed."""

    in_flight: bool
    now: float | None = None
    hit: float | None = None
    committed: float | None = None


@dataclass(frozen=True)
class Forward:
    """A braking deadline for an obstacle hit at `hit` (the race's own first estimate:
    `names` ""; else another pop-up's, `names` its ids), and the stop for the deadline: none,
    planning or done, and its start when done with a trajectory (None otherwise)."""

    deadline: float
    hit: float
    names: str
    stop: str
    start: float | None


@dataclass(frozen=True)
class Tick:
    """A turn of the race, the replan still out: whether the flight still holds control (else
    `flight`: its state's name), the stop for the deadline (as in Forward), whether it was asked
    for (`StopGuard.prepare`), and the trajectory time committed (None: not read, out of control)."""

    in_control: bool
    flight: str
    stop: str
    asked: bool
    start: float | None
    committed: float | None


@dataclass(frozen=True)
class ReplanOver:
    """The replan ended: swapped in (`ok`), or why not, the mission index of a blocked waypoint
    and its message; `error`: the repr of the exception it raised ("" none)."""

    ok: bool
    reason: str = ""
    blocked: int | None = None
    blocked_message: str = ""
    error: str = ""


@dataclass(frozen=True)
class ReplanCancelled:
    """The late replan cancelled and awaited: the notes it had made by then."""

    notes: tuple[str, ...]


@dataclass(frozen=True)
class PreparedSwap:
    """Whether the stop prepared for the deadline was swapped in; if not, its message (None:
    none was planned)."""

    swapped: bool
    message: str | None


Observation = PopUp | Forward | Tick | ReplanOver | ReplanCancelled | PreparedSwap


# -- actions -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Announce:
    """Say the obstacles were taken in; nothing else (no mission flown under our control)."""


@dataclass(frozen=True)
class Clear:
    """Announce, then say `event`: the flown plan stays clear, no replan."""

    event: str


@dataclass(frozen=True)
class Race:
    """Replan against the braking deadline (`state.hit`)."""


@dataclass(frozen=True)
class Forwarded:
    """The deadline was brought forward (`cancel`: drop the stop planned or planning for the
    later one) or not (`moved` False)."""

    moved: bool
    cancel: bool = False


@dataclass(frozen=True)
class GiveUp:
    """The flight no longer holds control: cancel the replan and the stop, and end."""


@dataclass(frozen=True)
class Prepare:
    """Plan the stop for the deadline now, then look again."""


@dataclass(frozen=True)
class Wait:
    """First plan the stop (`prepare`), then wait up to `timeout` s for the replan, and for the
    stop's planning (`stop`) or for it to be asked for (`asked`)."""

    timeout: float
    prepare: bool
    stop: bool
    asked: bool


@dataclass(frozen=True)
class Deadline:
    """The stop's start is near (`prepare`: plan it first): cancel the replan, await it, say its notes."""

    prepare: bool


@dataclass(frozen=True)
class Won:
    """The replan was swapped in: cancel the stop, end."""


@dataclass(frozen=True)
class Brake:
    """Brake for `reason` now (Brakes.brake: a stop planned now, else the one `prepared` for the
    deadline if it still starts ahead, else a hold), naming the `blocked` waypoint."""

    reason: str
    blocked: int | None = None
    prepared: bool = False


@dataclass(frozen=True)
class SwapPrepared:
    """Swap in the stop prepared for the deadline (waiting for its planning if need be)."""

    reason: str


@dataclass(frozen=True)
class Braked:
    """The prepared stop was swapped in: Braking for `reason`, said with the deadline and hit."""

    reason: str
    deadline: float
    hit: float


Action = Announce | Clear | Race | Forwarded | GiveUp | Prepare | Wait | Deadline | Won | Brake | SwapPrepared | Braked
Step = tuple[RaceState, Action]

# what each phase takes (Forward: any phase of a race, even while its brake is planned)
_TAKES: dict[str, tuple[type, ...]] = {POPUP: (PopUp,), RACING: (Forward, Tick, ReplanOver),
                                       CANCELLING: (Forward, ReplanCancelled), SWAPPING: (Forward, PreparedSwap),
                                       ENDED: (Forward,)}


def _popup(rules: RaceRules, o: PopUp) -> Step:
    ended = RaceState(ENDED)
    if not o.in_flight:
        return ended, Announce()
    if o.hit is None:
        return ended, Clear(f"obstacles {rules.names}: the current trajectory stays clear; no replan")
    assert o.committed is not None and o.now is not None
    if o.hit < o.committed + rules.split_ahead:  # setpoints up to now + lead are sent
        return ended, Brake(f"obstacle {rules.names} is {o.hit - o.now:.2f} s ahead: too close to replan")
    return racing(o.hit), Race()


def _forward(s: RaceState, o: Forward) -> Step:
    assert s.deadline is not None and s.hit is not None
    if o.deadline >= s.deadline:
        return s, Forwarded(False)
    notes = s.notes
    if o.names:
        notes = (*notes, f"deadline brought forward by obstacles {o.names} (hit at t={o.hit:.2f} s)")
    # a stop planned for the later deadline (or still planning for it) is dropped
    cancel = o.stop != NONE and (o.start is None or o.start > o.deadline)
    return replace(s, deadline=o.deadline, hit=min(s.hit, o.hit), notes=notes), Forwarded(True, cancel)


def _tick(rules: RaceRules, s: RaceState, o: Tick) -> Step:
    if not o.in_control:  # e.g. a pilot took over meanwhile
        return replace(s, phase=ENDED), GiveUp()
    assert s.deadline is not None and o.committed is not None
    prepare = o.stop == NONE and o.asked  # asked for: planned at once
    planning = o.stop != NONE or prepare
    # the stop's start: planned, or the deadline while it is not known yet
    wake = (s.deadline if o.start is None else o.start) - rules.spare
    if not planning:
        wake = min(wake, s.deadline - rules.prepare)
    delay = wake - o.committed  # a stop starts after the setpoints already sent
    if delay <= 0:
        if not planning:
            return s, Prepare()
        return replace(s, phase=CANCELLING), Deadline(prepare)
    # at most half a spare at a time: another pop-up may bring the deadline forward
    return s, Wait(min(delay, rules.spare / 2), prepare, prepare or o.stop == PLANNING, not planning)


def _replan_over(rules: RaceRules, s: RaceState, o: ReplanOver) -> Step:
    ok, reason, blocked = o.ok, o.reason, o.blocked
    if o.error:
        ok, reason, blocked = False, f"replan error: {o.error}", None
    if ok:
        return replace(s, phase=ENDED), Won()
    why = (f"{rules.what}: mission waypoint {blocked} is blocked ({o.blocked_message})" if blocked is not None
           else f"{rules.what}: no safe plan ({reason})")
    return replace(s, phase=ENDED), Brake(why, blocked, prepared=True)


def race_step(rules: RaceRules, s: RaceState, o: Observation) -> Step:
    """The new state and what to do next, for observation `o` (one `s.phase` takes)."""
    if not isinstance(o, _TAKES[s.phase]):
        raise ValueError(f"{type(o).__name__} observed in phase {s.phase!r}")
    if isinstance(o, PopUp):
        return _popup(rules, o)
    if isinstance(o, Forward):
        return _forward(s, o)
    if isinstance(o, Tick):
        return _tick(rules, s, o)
    if isinstance(o, ReplanOver):
        return _replan_over(rules, s, o)
    assert s.deadline is not None and s.hit is not None
    if isinstance(o, ReplanCancelled):
        pending = "; ".join([*o.notes, *s.notes, "the replan is still running"])
        reason = (f"{rules.what}: no verified replan by the braking deadline t={s.deadline:.2f} s "
                  f"(the plan enters the obstacle at t={s.hit:.2f} s; {pending})")
        return replace(s, phase=SWAPPING, reason=reason), SwapPrepared(reason)
    if o.swapped:
        return replace(s, phase=ENDED), Braked(s.reason, s.deadline, s.hit)
    return replace(s, phase=ENDED), Brake(s.reason + "; the prepared stop was not usable: "
                                          + ("none planned" if o.message is None else o.message))
