"""Which plan the navigator asks the planner for, and what it makes of the answer: one pure function.

`choice_step(rules, state, observation) -> (state, action)` decides the planner calls of three
runs, each a short sequence of attempts with fallbacks:
- a mission's start (companion/mission_start.py `MissionStart.fly`): with [planner] anytime, no
  durations given, fastest timing and no fleet, the default allocation first ("quick": flown at
  once, the search for the fastest durations follows, `improve`), the whole search when the
  quick plan is infeasible; the search otherwise (cut to what fits before the split: the plan
  budget's count), the separated start with a fleet. The quick choice is made once per start
  and lost when a quick plan fails, so the split loop's retries search. When nothing plans from
  a moving start, the search from further along the flown plan (`later`, twice);
- a replan of the flown mission (companion/replans.py `Replans._replan_outcome`): the local
  replan when the change or pop-up has a local edit, the remainder when it fails or has none;
- a stop (companion/braking.py `Brakes.brake`): a stop planned now; the stop prepared for the
  braking deadline when that one could not be swapped in; else hold at the measured position,
  unless the vehicle is no longer flown by us.
- the improvement of a quick start (`MissionStart.improve`): the search for the fastest
  durations of what is left, unless the flown plan changed first (before or after it), taken
  only if it lands at least `gain` s earlier;
- the `start` command (companion/commands.py `Commands.start`): take off when disarmed; take
  control back from a pilot, a failsafe or idle (refused on the ground but for PX4, which climbs
  in OFFBOARD); take off when ready on the ground; then fly the mission loaded, or resume the one
  a stop interrupted.
No I/O, no clock, no asyncio: the shell observes (the answer's status, whether the stop was
swapped in, whether we still fly), calls this, shows the call to the flight recorder
(/navigator/choice) and makes the call asked for. `python -m companion replay` runs each
recorded call again (companion/replay_choice.py) and checks that the planner calls the file
holds are the ones chosen.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

# the calls, as the recorder names the planner's functions (companion.record_format.function_name)
START = "companion.mission.start_mission"
SEPARATED = "companion.mission.start_separated"
LOCAL = "companion.mission.local_replan"
REMAINDER = "companion.mission.replan_remainder"
STOP = "companion.braking.plan_stop"
PREPARED = "the stop prepared for the braking deadline"  # planned before: only swapped in


@dataclass(frozen=True)
class StartRules:
    """A mission's start: [planner] anytime and timing, whether the mission gave durations,
    whether it is separated from other vehicles; `later`: how much further along the flown plan
    each of two more starts is tried when nothing plans from a moving one (0: none; recordings
    made before it replay with none)."""

    anytime: bool
    timing: str
    durations: bool
    fleet: bool
    later: float = 0.0


@dataclass(frozen=True)
class ReplanRules:
    """A replan: whether the change or pop-up has a local edit, whether durations are chosen again."""

    local: bool
    allocate: bool


@dataclass(frozen=True)
class StopRules:
    """A stop: whether a stop prepared for the braking deadline was handed over."""

    prepared: bool


@dataclass(frozen=True)
class StartCommand:
    """The `start` command: the altitude a take-off climbs to ([safety] takeoff_altitude)."""

    altitude: float


@dataclass(frozen=True)
class ImproveRules:
    """The improvement of a quick start: when the quick plan lands (trajectory time), and how much
    earlier the search's must land to replace it."""

    quick_end: float
    gain: float


Rules = StartRules | ReplanRules | StopRules | StartCommand | ImproveRules

CHANGED = "the flown plan changed first"
LATER_TRIES = 2  # a start's further starts along the flown plan (StartRules.later)
NO_EARLIER = "lands no earlier"

# the flight states from which `start` takes control back first (companion.flight.State values)
TAKEN_BACK_FROM = ("PILOT", "FAILSAFE", "IDLE")


@dataclass(frozen=True)
class ChoiceState:
    """`quick`: a start flies the default allocation (None: not decided yet); `last`: the call
    the last action asked for ("" before any); `why`: what the first answer of a stop said;
    `moving`, `later`: a start's split is not at rest, and how far past it the last call started."""

    quick: bool | None = None
    last: str = ""
    why: str = ""
    moving: bool = False
    later: float = 0.0


@dataclass(frozen=True)
class Ask:
    """The run (or a retry of the split loop) asks for a plan; `flying`: the vehicle is ours
    and flown (a stop only); `moving`: the flown plan is not at rest at the split (a start)."""

    flying: bool = True
    moving: bool = False


@dataclass(frozen=True)
class Answer:
    """What the last call gave: `ok` (a stop's: swapped in), the outcome's status name, its
    message; `flying`: still ours and flown (a stop), the quick plan still flown and nothing
    else planning (an improvement); `t_end`: when the plan lands (an improvement's)."""

    ok: bool
    status: str
    message: str
    flying: bool = True
    t_end: float = 0.0


@dataclass(frozen=True)
class Asked:
    """`start` arrives: the vehicle armed, the flight state (its value), airborne as the supervisor
    knows it, in the air as the autopilot reports it, which autopilot."""

    armed: bool
    state: str
    airborne: bool
    in_air: bool
    autopilot: str


@dataclass(frozen=True)
class Now:
    """After a take-off or taking control (or at once): the flight state, airborne, a mission
    loaded, a mission interrupted by a stop."""

    state: str
    airborne: bool
    pending: bool
    interrupted: bool


Observation = Ask | Answer | Asked | Now


@dataclass(frozen=True)
class Plan:
    """Make this call (`quick`: the default allocation; `allocate`: choose durations again;
    `later`: from the flown plan that many seconds after the split, which it flies until then)."""

    call: str
    quick: bool = False
    allocate: bool = False
    later: float = 0.0


@dataclass(frozen=True)
class Take:
    """The last answer stands (`ok` or not); `quick`: a start's default allocation flies and
    its search follows; `detail`: what a stop says it flies."""

    ok: bool
    call: str
    quick: bool = False
    detail: str = ""


@dataclass(frozen=True)
class Hold:
    """No stop could be swapped in: hold at the measured position, saying `detail`."""

    detail: str


@dataclass(frozen=True)
class Nothing:
    """The vehicle is no longer flown by us: nothing to stop."""


@dataclass(frozen=True)
class TakeOff:
    altitude: float


@dataclass(frozen=True)
class TakeControl:
    reason: str


@dataclass(frozen=True)
class Look:
    """Nothing to do first: observe `Now`."""


@dataclass(frozen=True)
class Refuse:
    """The companion's own check refuses (`by` the companion)."""

    reason: str


@dataclass(frozen=True)
class FlyPending:
    """Fly the mission loaded."""


@dataclass(frozen=True)
class Resume:
    """Resume the mission a stop interrupted."""


Action = Plan | Take | Hold | Nothing | TakeOff | TakeControl | Look | Refuse | FlyPending | Resume
Step = tuple[ChoiceState, Action]


def quick_start(rules: StartRules) -> bool:
    return rules.anytime and not rules.durations and rules.timing == "fastest" and not rules.fleet


def _start(rules: StartRules, state: ChoiceState, seen: Observation) -> Step:
    quick = quick_start(rules) if state.quick is None else state.quick
    if isinstance(seen, Ask):
        call = SEPARATED if rules.fleet else START
        return ChoiceState(quick, call, moving=seen.moving), Plan(call, quick=quick)
    assert isinstance(seen, Answer)
    if state.last == START and quick and not seen.ok and seen.status == "INFEASIBLE":
        # the default allocation failed where the search may not (it places knots, tries other
        # durations): the search, as without anytime, before refusing
        return replace(state, quick=False), Plan(START, later=state.later)
    if (not seen.ok and seen.status == "INFEASIBLE" and state.moving and rules.later > 0.0
            and state.later < LATER_TRIES * rules.later):
        # From some moving jets no degree-9 first segment reaches the first waypoint within the
        # bounds (planner_core.missions.lead_in); a little further along the flown plan, which
        # is verified and flies on meanwhile, the jet differs and the search plans it (missions
        # replaced in flight: 12 of 5600 splits refused from the jet, none from 0.25 s later).
        later = state.later + rules.later
        return replace(state, quick=False, later=later), Plan(state.last, later=later)
    quick = quick and seen.ok  # a failed quick plan: the split loop's retries search
    return replace(state, quick=quick), Take(seen.ok, state.last, quick)


def _replan(rules: ReplanRules, state: ChoiceState, seen: Observation) -> Step:
    if isinstance(seen, Ask):
        call = LOCAL if rules.local else REMAINDER
        return ChoiceState(None, call), Plan(call, allocate=rules.allocate and call == REMAINDER)
    assert isinstance(seen, Answer)
    if state.last == LOCAL and not seen.ok:
        return ChoiceState(None, REMAINDER), Plan(REMAINDER, allocate=rules.allocate)
    return state, Take(seen.ok, state.last)


def _stop(rules: StopRules, state: ChoiceState, seen: Observation) -> Step:
    if isinstance(seen, Ask):
        if not seen.flying:
            return state, Nothing()
        return ChoiceState(None, STOP), Plan(STOP)
    assert isinstance(seen, Answer)
    why = seen.message if state.last == STOP else state.why
    if seen.ok:
        detail = why if state.last == STOP else f"{why}; the stop prepared for the braking deadline instead"
        return ChoiceState(None, state.last, why), Take(True, state.last, detail=detail)
    if state.last == STOP and rules.prepared:
        return ChoiceState(None, PREPARED, why), Plan(PREPARED)
    if not seen.flying:
        return ChoiceState(None, state.last, why), Nothing()
    return (ChoiceState(None, state.last, why),
            Hold(f"no verified braking trajectory ({why}); holding at the measured position"))


def _command(rules: StartCommand, state: ChoiceState, seen: Observation) -> Step:
    if isinstance(seen, Asked):
        after = ChoiceState(None, "ready")
        if not seen.armed:
            return after, TakeOff(rules.altitude)
        if seen.state in TAKEN_BACK_FROM:
            if not seen.airborne and not seen.in_air and seen.autopilot != "px4":
                return ChoiceState(None, "refused"), Refuse("vehicle is on the ground: send 'takeoff' first")
            return after, TakeControl("start command: taking control")
        return after, Look()
    assert isinstance(seen, Now)
    if state.last == "ready" and seen.state == "READY" and not seen.airborne:
        return ChoiceState(None, "fly"), TakeOff(rules.altitude)
    done = ChoiceState(None, "done")
    if seen.pending:
        return done, FlyPending()
    if seen.interrupted:
        return done, Resume()
    return done, Nothing()


def _improve(rules: ImproveRules, state: ChoiceState, seen: Observation) -> Step:
    # `flying`: the quick plan is still the one flown, and nothing else holds the navigator
    if isinstance(seen, Ask):
        if not seen.flying:
            return ChoiceState(None, ""), Take(False, "", detail=CHANGED)
        return ChoiceState(None, REMAINDER), Plan(REMAINDER, allocate=True)
    assert isinstance(seen, Answer)
    if not seen.flying:
        return state, Take(False, state.last, detail=CHANGED)
    if seen.ok and seen.t_end > rules.quick_end - rules.gain:
        return state, Take(False, state.last, detail=NO_EARLIER)
    return state, Take(seen.ok, state.last)


def choice_step(rules: Rules, state: ChoiceState, seen: Observation) -> Step:
    if isinstance(rules, ImproveRules):
        return _improve(rules, state, seen)
    if isinstance(rules, StartCommand):
        return _command(rules, state, seen)
    if isinstance(rules, StartRules):
        return _start(rules, state, seen)
    if isinstance(rules, ReplanRules):
        return _replan(rules, state, seen)
    return _stop(rules, state, seen)
