"""The operator commands' sequences' decisions, as one pure function.

`command_step(rules, state, observation) -> (state, action)` decides, for one run of one
sequence of companion/commands.py (`CommandRules.sequence`), what the sequence does next from
what it observed: the autopilot's answer to a command or its absence (a timeout), the mode and
armed state seen, the flight state, the swap's refusal of a climb and how long its plan took,
and how a whole command ended. The sequences:
- "follow": take control for OFFBOARD/GUIDED (PX4: setpoints streaming first, PX4 refuses
  OFFBOARD without them), ask for the mode and wait for it;
- "arm": follow, then arm; a denial leaves the autopilot in the mode it was in (restored);
- "takeoff": arm or follow as needed, then the PX4 climb or ArduPilot's takeoff, then a pending
  mission that starts on its own;
- "climb": PX4's verified climb swapped in, a late plan moved later from the hold or planned
  again once further ahead (as companion/split_rules.py does for missions);
- "land", "on_ground", "abort", "disarm";
- "outcome": how a sequence run as a command ended (completed, refused and by whom, cancelled).
No I/O, no clock, no asyncio: the sequence (Commands, companion/commands.py) observes, calls
this, shows the call to the flight recorder (/commands/step) and carries out the action; the
waits (timeouts, acknowledgements) stay there. A sub-sequence (arm inside takeoff, the climb)
is a run of its own, with its own steps. `python -m companion replay` runs each recorded call
again (companion/replay_commands.py).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

from companion.control import SWAP_LATE
from companion.flight import HOLDING_CONTROL, State
from companion.plan_budget import MAX_AHEAD, RETRY_MARGIN

SEQUENCES = ("follow", "arm", "takeoff", "climb", "land", "on_ground", "abort", "disarm", "outcome")
# MAVLink commands (Send.command) and waits (Await.until) the shell knows how to carry out
COMMANDS = ("follow_mode", "arm", "disarm", "restore_mode", "land", "takeoff")
WAITS = ("follow", "armed", "mode", "altitude", "climb", "on_ground")
# supervisor events a sequence makes (Transition.event): companion.supervisor's classes
EVENTS = ("TakingControl", "ArmRequested", "Armed", "TakeoffBegan", "TookOff", "LandRequested", "SequenceAborted",
          "DisarmRequested", "DisarmedOnCommand")
BEGIN, ENDED = "begin", "ended"
_HOLDING = frozenset(s.value for s in HOLDING_CONTROL)
_FOLLOWED = (State.READY.value, State.HOLDING.value)  # a takeoff from these needs no OFFBOARD/GUIDED again


@dataclass(frozen=True)
class CommandRules:
    """One run's givens: the sequence, and what it was asked for: why control is taken
    ("follow"), the altitude and what it is above ("takeoff"), the split's lead, the retry's
    limits and the climb's target z ("climb"), the command a sequence ran for ("outcome")."""

    sequence: str
    reason: str = ""
    altitude: float = 0.0
    ahead: float = 0.0
    target_z: float = 0.0
    command: str = ""
    retry_margin: float = RETRY_MARGIN
    max_ahead: float = MAX_AHEAD


@dataclass(frozen=True)
class CommandState:
    """What a run remembers: what it waits for next (`expect`: the observation's kind) and the
    action it last asked for (`at`), the autopilot, the mode before arming (restored after a
    denial) and the denial itself, the takeoff's target, and the climb's attempt, split, the time
    its plan took, the later split and when it ends."""

    expect: str = BEGIN
    at: str = ""
    autopilot: str = ""
    before_mode: str = ""
    before_base: int = 0
    before_custom: int = 0
    denial: str = ""
    target_z: float = 0.0
    above: str = ""
    home_z: float = 0.0
    ahead: float = 0.0
    attempt: int = 0
    t_split: float = 0.0
    took: float = 0.0
    end: float = 0.0


# -- observations -----------------------------------------------------------------------------


@dataclass(frozen=True)
class Begin:
    """What a run starts from: the autopilot, armed, its mode (name, base and custom), the
    flight state's name, whether Control streams setpoints, and the height above the ground
    where the vehicle stood (0: not known)."""

    autopilot: str
    armed: bool
    mode: str
    base_mode: int
    custom_mode: int
    flight: str
    streaming: bool
    height: float


@dataclass(frozen=True)
class Did:
    """The action carried out: whether it `failed` (a CommandFailed: its text `error`, who
    failed `by` and the autopilot's MAV_RESULT, None: none), then armed, the mode and whether
    the vehicle is airborne as seen right after."""

    failed: bool
    error: str
    by: str
    result: str | None
    armed: bool
    mode: str
    airborne: bool


@dataclass(frozen=True)
class Aimed:
    """The takeoff's target (local z, NED), what it is above, home's z (or where the vehicle
    is, without home: ArduPilot's takeoff altitude is above home) and the autopilot."""

    target_z: float
    above: str
    home_z: float
    autopilot: str


@dataclass(frozen=True)
class Pending:
    """After the takeoff: whether a mission waits that starts on its own (and no start runs)."""

    autostart: bool


@dataclass(frozen=True)
class ClimbFrom:
    """The trajectory time committed when the climb starts (Control flies its hold)."""

    committed: float


@dataclass(frozen=True)
class ClimbPlanned:
    """The climb's plan: `ok` (with a trajectory, ending at `end`), else its message, and the
    seconds it took."""

    ok: bool
    message: str
    took: float
    end: float


@dataclass(frozen=True)
class ClimbSwapped:
    """Control.swap's refusal of the climb ("" swapped in), whether Control still flies, and
    the trajectory time committed right after."""

    refusal: str
    flying: bool
    committed: float


@dataclass(frozen=True)
class ClimbMoved:
    """The same climb moved to the later split: whether the flown plan holds still until then,
    whether it was swapped in there (ending at `end`), and the time committed right after."""

    held: bool
    moved: bool
    committed: float
    end: float


@dataclass(frozen=True)
class Ended:
    """How a sequence run as a command ended: `failed` (a CommandFailed: its text `error`,
    `by`, whether the autopilot gave a MAV_RESULT), or `cancelled`; and PX4's last arming-check
    report (`checks`: how many reasons, `said` joined by "; ", `age` seconds before)."""

    failed: bool
    error: str
    by: str
    result: bool
    cancelled: bool
    checks: int
    said: str
    age: float


Observation = Begin | Did | Aimed | Pending | ClimbFrom | ClimbPlanned | ClimbSwapped | ClimbMoved | Ended


# -- actions -----------------------------------------------------------------------------------


@dataclass(frozen=True)
class Transition:
    """Hand the supervisor `event` (EVENTS) with its `reason`, `mode` or `armed`."""

    event: str
    reason: str = ""
    mode: str = ""
    armed: bool = False


@dataclass(frozen=True)
class TakeControl:
    """Control holds at the measured position (the supervisor: ControlTaken); `stream`: the
    setpoints sent are counted just before, for the Stream that follows."""

    reason: str
    stream: bool = False


@dataclass(frozen=True)
class Stream:
    """Wait for the first setpoint to leave after the TakeControl before (at most 3 s), then let
    them stream 1.1 s: PX4 refuses OFFBOARD unless setpoints have been streaming for a while
    (COM_OF_LOSS_T, 1 s)."""


@dataclass(frozen=True)
class Send:
    """Send a MAVLink command (COMMANDS) and await its answer: the mode to restore (`base`,
    `custom`), the takeoff's altitude above home (ArduPilot; Control is paused first)."""

    command: str
    base: int = 0
    custom: int = 0
    altitude: float = 0.0


@dataclass(frozen=True)
class Await:
    """Wait (WAITS) at most `timeout` seconds (the climb: until its `end` + 10 s) for `what`:
    the `mode`, the altitude `z` (at rest)."""

    until: str
    timeout: float
    what: str
    mode: str = ""
    z: float = 0.0
    end: float = 0.0


@dataclass(frozen=True)
class Run:
    """Run a sequence of its own (`follow` with `reason`, `arm`, `climb`) and observe how it ended."""

    sequence: str
    reason: str = ""


@dataclass(frozen=True)
class Aim:
    """Where the takeoff ends (Commands.takeoff_target)."""


@dataclass(frozen=True)
class CheckPending:
    """Is a mission waiting that starts on its own?"""


@dataclass(frozen=True)
class FlyPending:
    """Fly the pending mission."""


@dataclass(frozen=True)
class AbortMission:
    """The navigator aborts what Control flies (a stop)."""


@dataclass(frozen=True)
class Forget:
    """Control forgets what it flew (nothing of ours is flown)."""


@dataclass(frozen=True)
class Release:
    """Stop commanding at once, and cancel the running sequence."""


@dataclass(frozen=True)
class PlanClimb:
    """Plan the climb from the flown plan at `t_split`."""

    t_split: float


@dataclass(frozen=True)
class SwapClimb:
    """Swap the climb in at `t_split`."""

    t_split: float


@dataclass(frozen=True)
class MoveClimb:
    """If the flown plan holds still from `t_split` to `t_later`, swap the same climb in, moved there."""

    t_split: float
    t_later: float


@dataclass(frozen=True)
class Say:
    """Report the event `kind` with `text`."""

    kind: str
    text: str


@dataclass(frozen=True)
class Refuse:
    """Report `command` refused for `reason`, by whom; `checks`: with PX4's arming checks."""

    command: str
    reason: str
    by: str
    checks: bool = False


@dataclass(frozen=True)
class Complete:
    """Report `command` completed."""

    command: str


@dataclass(frozen=True)
class Fail:
    """The run fails (CommandFailed): `how` "again": the failure just observed, as it was;
    "chained": the run's first failure (the denial) with the longer `message`; "new": a new one
    with `message`, `by`."""

    how: str
    message: str = ""
    by: str = "companion"


@dataclass(frozen=True)
class Finish:
    """The run ends (`ok`: land and disarm say whether the command went through)."""

    ok: bool = True


Action = (Transition | TakeControl | Stream | Send | Await | Run | Aim | CheckPending | FlyPending | AbortMission
          | Forget | Release | PlanClimb | SwapClimb | MoveClimb | Say | Refuse | Complete | Fail | Finish)
Step = tuple[CommandState, Action]


def _to(s: CommandState, at: str, action: Action, expect: str = "did") -> Step:
    return replace(s, at=at, expect=expect), action


def _end(s: CommandState, action: Action) -> Step:
    return replace(s, at="end", expect=ENDED), action


def _follow(rules: CommandRules, s: CommandState, o: Observation) -> Step:
    if isinstance(o, Begin):
        return _to(replace(s, autopilot=o.autopilot), "taking", Transition("TakingControl", rules.reason))
    assert isinstance(o, Did)
    if s.at == "taking":
        if s.autopilot == "px4":  # streaming first: PX4 refuses OFFBOARD without setpoints
            return _to(s, "take", TakeControl(rules.reason, stream=True))
        return _to(s, "mode", Send("follow_mode"))
    if s.at == "take":
        return _to(s, "stream", Stream())
    if s.at == "stream":
        return _to(s, "mode", Send("follow_mode"))
    if s.at == "mode":
        return _to(s, "confirm", Await("follow", 3.0, "the autopilot to confirm OFFBOARD/GUIDED"))
    if s.at == "confirm" and s.autopilot != "px4" and o.airborne:  # ArduPilot: control once GUIDED, in the air
        return _to(s, "taken", TakeControl(rules.reason))
    return _end(s, Finish())


def _arm(s: CommandState, o: Observation) -> Step:
    if isinstance(o, Begin):
        s = replace(s, autopilot=o.autopilot, before_mode=o.mode, before_base=o.base_mode, before_custom=o.custom_mode)
        return _to(s, "follow", Run("follow", "arm command"))
    assert isinstance(o, Did)
    if s.at in ("arm", "armed?") and o.failed:
        # denied: leave the autopilot in the mode it was in, not in OFFBOARD/GUIDED
        if o.armed or not s.before_mode or o.mode == s.before_mode:
            return _end(s, Fail("again"))
        return _to(replace(s, denial=o.error), "restore", Send("restore_mode", s.before_base, s.before_custom))
    if s.at in ("restore", "restored"):
        if o.failed:
            return _end(s, Fail("chained", f"{s.denial}; and the previous mode {s.before_mode} was not restored: "
                                           f"{o.error}"))
        if s.at == "restore":
            return _to(s, "restored", Await("mode", 3.0, f"the autopilot to confirm {s.before_mode}",
                                            mode=s.before_mode))
        return _end(s, Fail("chained", f"{s.denial}; the autopilot is back in {s.before_mode}"))
    if o.failed:
        return _end(s, Fail("again"))
    if s.at == "follow":
        return _to(s, "requested", Transition("ArmRequested"))
    if s.at == "requested":
        return _to(s, "arm", Send("arm"))
    if s.at == "arm":
        return _to(s, "armed?", Await("armed", 3.0, "the autopilot to report armed"))
    if s.at == "armed?":
        return _to(s, "armed", Transition("Armed", mode=o.mode))
    return _end(s, Finish())


def _takeoff(rules: CommandRules, s: CommandState, o: Observation) -> Step:
    alt = rules.altitude
    if isinstance(o, Begin):
        s = replace(s, autopilot=o.autopilot)
        if not o.armed:
            return _to(s, "arm", Run("arm"))
        if o.flight not in _FOLLOWED:
            return _to(s, "follow", Run("follow", "takeoff command"))
        return _to(s, "aim", Aim(), "aimed")
    if isinstance(o, Aimed):
        s = replace(s, target_z=o.target_z, above=o.above, home_z=o.home_z, autopilot=o.autopilot)
        return _to(s, "began", Transition(
            "TakeoffBegan", f"taking off to {alt:.2f} m above {o.above} (local z {o.target_z:.2f} m NED)"))
    if isinstance(o, Pending):
        return _to(s, "fly", FlyPending()) if o.autostart else _end(s, Finish())
    assert isinstance(o, Did)
    if o.failed:
        return _end(s, Fail("again"))
    if s.at in ("arm", "follow"):
        return _to(s, "aim", Aim(), "aimed")
    if s.at == "began":
        if s.autopilot == "px4":
            return _to(s, "climb", Run("climb"))
        return _to(s, "send", Send("takeoff", altitude=max(0.1, s.home_z - s.target_z)))  # above home
    if s.at == "send":
        return _to(s, "rise", Await("altitude", 10.0 + alt / 0.3, f"altitude {alt:.2f} m, at rest", z=s.target_z))
    if s.at == "rise":
        return _to(s, "complete", TakeControl("takeoff complete"))
    if s.at in ("climb", "complete"):
        return _to(s, "tookoff", Transition("TookOff", f"airborne at {alt:.2f} m above {s.above}: holding"))
    if s.at == "tookoff":
        return _to(s, "pending", CheckPending(), "pending")
    return _end(s, Finish())


def _climb(rules: CommandRules, s: CommandState, o: Observation) -> Step:
    if isinstance(o, ClimbFrom):
        t_split = o.committed + rules.ahead
        return _to(replace(s, ahead=rules.ahead, t_split=t_split), "plan", PlanClimb(t_split), "planned")
    if isinstance(o, ClimbPlanned):
        s = replace(s, took=o.took, end=o.end)
        if not o.ok:
            return _end(s, Fail("new", f"no verified climb: {o.message}"))
        return _to(s, "swap", SwapClimb(s.t_split), "swapped")
    if isinstance(o, ClimbSwapped):
        if o.refusal == "":
            return _wait_climb(rules, s)
        if not o.flying:
            return _end(s, Fail("new", "control was released during the climb's planning"))
        if o.refusal != SWAP_LATE or s.attempt == 1:
            return _end(s, Fail("new", f"climb not swapped in: {o.refusal}"
                                + (f" (planning took {s.took:.2f} s, twice)" if s.attempt == 1 else "")))
        # planned too late on a busy computer: from a hold the same climb starts later just as
        # well (the curve and its checks do not depend on the time), so it is moved, not replanned
        ahead = min(max(2.0 * s.ahead, rules.retry_margin * s.took + 0.1), rules.max_ahead)
        return _to(replace(s, ahead=ahead), "move", MoveClimb(s.t_split, o.committed + ahead), "moved")
    if isinstance(o, ClimbMoved):
        if o.moved:
            return _wait_climb(rules, replace(s, end=o.end))
        t_split = o.committed + s.ahead  # planned again once, further ahead
        return _to(replace(s, attempt=1, t_split=t_split), "plan", PlanClimb(t_split), "planned")
    assert isinstance(o, Did)
    return _end(s, Fail("again") if o.failed else Finish())


def _wait_climb(rules: CommandRules, s: CommandState) -> Step:
    return _to(s, "wait", Await("climb", 0.0, "the climb to finish, at rest", z=rules.target_z, end=s.end))


def _land(s: CommandState, o: Observation) -> Step:
    if isinstance(o, Begin):
        return _to(s, "requested", Transition("LandRequested"))
    assert isinstance(o, Did)
    if s.at == "requested":
        return _to(s, "send", Send("land"))
    if s.at == "send" and o.failed:
        return _to(s, "refused", Refuse("land", f"failed: {o.error}", "autopilot"))
    return _end(s, Finish(s.at == "send"))


def _disarm(s: CommandState, o: Observation) -> Step:
    if isinstance(o, Begin):
        return _to(s, "requested", Transition("DisarmRequested"))
    assert isinstance(o, Did)
    if s.at == "requested":
        return _to(s, "release", Release())
    if s.at == "release":
        return _to(s, "send", Send("disarm"))
    if s.at == "send" and o.failed:
        return _to(s, "refused", Refuse("disarm", f"failed: {o.error}", "autopilot"))
    if s.at == "send":
        return _to(s, "disarmed", Transition("DisarmedOnCommand", "disarmed on command"))
    return _end(s, Finish(s.at == "disarmed"))


def _abort(s: CommandState, o: Observation) -> Step:
    if isinstance(o, Begin):
        if o.flight in _HOLDING or (o.flight == State.TAKEOFF.value and o.streaming):
            return _to(s, "mission", AbortMission())
        return _to(s, "forget", Forget())
    assert isinstance(o, Did)
    if o.failed and s.at == "mission":
        return _end(s, Fail("again"))
    if s.at == "forget":
        return _to(s, "aborted", Transition("SequenceAborted", "abort command", armed=o.armed))
    if s.at in ("mission", "aborted"):
        return _to(s, "said", Say("aborted", "mission and pending commands cancelled"))
    return _end(s, Finish())


def _outcome(rules: CommandRules, s: CommandState, o: Observation) -> Step:
    name = rules.command
    if isinstance(o, Ended):
        if o.cancelled:
            return _to(s, "cancelled", Refuse(name, "cancelled before it completed", "companion"))
        if not o.failed:
            return _to(s, "completed", Complete(name))
        # the companion's own checks say why; the autopilot's refusals say what failed
        reason = o.error if o.by == "companion" else f"failed: {o.error}"
        checks = o.by == "autopilot" and o.result and name in ("arm", "takeoff", "start") and o.checks > 0
        if checks:
            reason += f"; PX4's arming checks ({o.age:.1f} s before): {o.said}"
        return _to(replace(s, denial=o.error), "refused", Refuse(name, reason, o.by, checks))
    assert isinstance(o, Did)
    if s.at == "refused":
        return _to(s, "aborted", Transition("SequenceAborted", f"{name} failed: {s.denial}", armed=o.armed))
    return _end(s, Finish())


_BEGINS: dict[str, type] = {"climb": ClimbFrom, "outcome": Ended}
_EXPECTS: dict[type, str] = {Begin: BEGIN, ClimbFrom: BEGIN, Ended: BEGIN, Did: "did", Aimed: "aimed",
                             Pending: "pending", ClimbPlanned: "planned", ClimbSwapped: "swapped", ClimbMoved: "moved"}


def command_step(rules: CommandRules, s: CommandState, o: Observation) -> Step:
    """The new state and what to do next, for observation `o` (the kind `s.expect` names)."""
    if rules.sequence not in SEQUENCES:
        raise ValueError(f"{rules.sequence!r} is not a command sequence")
    if s.expect != _EXPECTS[type(o)] or (s.expect == BEGIN and type(o) is not _BEGINS.get(rules.sequence, Begin)):
        raise ValueError(f"{type(o).__name__} observed while {rules.sequence} waits for {s.expect!r}")
    seq = rules.sequence
    if seq == "follow":
        if isinstance(o, Did) and o.failed:
            return _end(s, Fail("again"))
        return _follow(rules, s, o)
    if seq == "arm":
        return _arm(s, o)
    if seq == "takeoff":
        return _takeoff(rules, s, o)
    if seq == "climb":
        return _climb(rules, s, o)
    if seq == "land":
        return _land(s, o)
    if seq == "on_ground":
        if isinstance(o, Begin):
            return _to(s, "wait", Await("on_ground", 30.0 + o.height / 0.3, "the vehicle to be on the ground"))
        assert isinstance(o, Did)
        return _end(s, Fail("again") if o.failed else Finish())
    if seq == "disarm":
        return _disarm(s, o)
    if seq == "abort":
        return _abort(s, o)
    return _outcome(rules, s, o)
