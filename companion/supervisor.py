"""The supervisor: the one writer of the flight state.

`transition(state, event) -> (new state, actions)` is pure: no sockets, no clock, no
callbacks. The modules that see something happen (the autopilot watch, the commands, the
navigator, the brakes) submit a small typed event to `Supervisor.handle`; the supervisor
replaces its `FlightState` with the one `transition` returns and carries out the actions
through the sinks the service connected (publish the state event, stop commanding, ...).
Everyone else reads the state through the supervisor's properties, never writes it.

Every `handle` call is also shown to an observer the shell connects (the flight recorder's
`Tap.transition`: `python -m companion replay` runs the recorded calls through `transition`
again). The supervisor knows only a callable; `transition` knows nothing of it.

The policies about what the vehicle did on its own (a disarm, a mode we did not ask for, the
link lost, the companion stalled) are here, next to the transitions they cause.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field, replace
from typing import Any

from companion.flight import (
    IN_OUR_MODE,
    FlightState,
    State,
    go,
    on_link,
    on_mode_report,
)

S = State
log = logging.getLogger("companion")

# -- events: what happened, as the module that saw it says -----------------------------------


@dataclass(frozen=True)
class ControlTaken:
    """We stream setpoints of our own again: a mode change from now on is not one we asked for."""


@dataclass(frozen=True)
class ExitRequested:
    """We ask the autopilot to leave our mode (a hand-over): not a pilot takeover."""


@dataclass(frozen=True)
class ArmRequested:
    """We ask for an arm: a later disarm is not ours unless asked again."""


@dataclass(frozen=True)
class DisarmRequested:
    """We ask for a disarm: it is not a failsafe."""


@dataclass(frozen=True)
class StartBegan:
    pass


@dataclass(frozen=True)
class StartEnded:
    pass


@dataclass(frozen=True)
class Heartbeat:
    """A heartbeat from the autopilot: the link is up."""


@dataclass(frozen=True)
class GroundLearnt:
    """The vehicle stands disarmed at local z (NED)."""

    z: float


@dataclass(frozen=True)
class LandedStateReport:
    """EXTENDED_SYS_STATE's landed state, as two facts."""

    in_air: bool  # in the air or landing
    on_ground: bool


@dataclass(frozen=True)
class HeightReport:
    """Without a landed state: in the air or on the ground by height and speed (the watch's
    timers decide when)."""

    airborne: bool


@dataclass(frozen=True)
class Disarmed:
    """A heartbeat says disarmed."""

    mode: str
    stalled: bool  # the companion stalled or just woke from a stall


@dataclass(frozen=True)
class ModeReport:
    """An armed heartbeat: whether the autopilot is in our mode (OFFBOARD/GUIDED)."""

    in_our_mode: bool
    mode: str
    stalled: bool


@dataclass(frozen=True)
class LinkLost:
    timeout: float  # s without a heartbeat


@dataclass(frozen=True)
class Stalled:
    """The companion stalled long enough that setpoints stopped: it stops commanding."""

    reason: str


@dataclass(frozen=True)
class TakingControl:
    """We stream a hold and ask for our mode (arm, takeoff, start)."""

    reason: str


@dataclass(frozen=True)
class Armed:
    mode: str


@dataclass(frozen=True)
class ControlTakenBack:
    """`start` from PILOT/FAILSAFE/IDLE: the autopilot is in our mode again."""

    mode: str


@dataclass(frozen=True)
class TakeoffBegan:
    reason: str


@dataclass(frozen=True)
class TookOff:
    reason: str


@dataclass(frozen=True)
class TakeoffInterrupted:
    reason: str


@dataclass(frozen=True)
class SequenceAborted:
    """An arm/takeoff sequence ended early (failed, aborted, interrupted by the exit)."""

    reason: str
    armed: bool


@dataclass(frozen=True)
class ExitBegan:
    """The service exits; `flying`: our setpoint stream flies a plan."""

    reason: str
    flying: bool


@dataclass(frozen=True)
class LandRequested:
    pass


@dataclass(frozen=True)
class DisarmedOnCommand:
    reason: str


@dataclass(frozen=True)
class HandedOver:
    """The autopilot confirmed the mode we handed the vehicle over to."""

    reason: str
    mode: str
    landing: bool


@dataclass(frozen=True)
class MissionStarted:
    mission_id: str


@dataclass(frozen=True)
class ReplanFlown:
    what: str


@dataclass(frozen=True)
class MissionComplete:
    mission_id: str


@dataclass(frozen=True)
class StoppedAfterBraking:
    pass


@dataclass(frozen=True)
class Braking:
    reason: str


Event = (ControlTaken | ExitRequested | ArmRequested | DisarmRequested | StartBegan | StartEnded | Heartbeat
         | GroundLearnt | LandedStateReport | HeightReport | Disarmed | ModeReport | LinkLost | Stalled
         | TakingControl | Armed | ControlTakenBack | TakeoffBegan | TookOff | TakeoffInterrupted | SequenceAborted
         | ExitBegan | LandRequested | DisarmedOnCommand | HandedOver | MissionStarted | ReplanFlown | MissionComplete
         | StoppedAfterBraking | Braking)

# -- actions: what the shell does about it -----------------------------------------------------


@dataclass(frozen=True)
class Announce:
    """Publish the state transition (event `state`) with its reason."""

    src: State
    dst: State
    reason: str


@dataclass(frozen=True)
class Release:
    """Stop commanding at once and cancel a running command sequence."""


@dataclass(frozen=True)
class StopStream:
    """Stop the setpoint stream (the sequence that is running ends by itself)."""


@dataclass(frozen=True)
class Say:
    """Publish an event of `kind` (failsafe, pilot_takeover, link_lost)."""

    kind: str
    message: str
    fields: Mapping[str, Any] = field(default_factory=dict)


Action = Announce | Release | StopStream | Say
Step = tuple[FlightState, tuple[Action, ...]]
# what an observer of `Supervisor.handle` is shown: the state before, the event, the state after
# and the actions, once per call
Observer = Callable[[FlightState, Event, FlightState, tuple[Action, ...]], None]


def _to(fs: FlightState, to: State, reason: str, *before: Action) -> Step:
    new, ev = go(fs, to, reason)
    return new, (*before, *(() if ev is None else (Announce(fs.state, to, reason),)))


def transition(fs: FlightState, event: Event) -> Step:
    """The new state and what to do for `event` in `fs`. Raises IllegalTransition for a
    transition the table does not allow (a bug in the caller)."""
    match event:
        case ControlTaken():
            return replace(fs, exit_requested=False), ()
        case ExitRequested():
            return replace(fs, exit_requested=True), ()
        case ArmRequested():
            return replace(fs, disarm_requested=False), ()
        case DisarmRequested():
            return replace(fs, disarm_requested=True), ()
        case StartBegan():
            return replace(fs, starting=True), ()
        case StartEnded():
            return replace(fs, starting=False), ()
        case Heartbeat():
            return replace(fs, seen_link=True, link_lost=False), ()
        case GroundLearnt(z):
            return replace(fs, ground_z=z), ()
        case LandedStateReport(in_air, on_ground):
            if in_air:
                return replace(fs, airborne=True), ()
            if on_ground and fs.state is not S.TAKEOFF:
                # our own takeoff sets `airborne` when it completes; otherwise the autopilot knows
                return replace(fs, airborne=False), ()
            return fs, ()
        case HeightReport(airborne):
            if fs.state in (S.ARMING, S.TAKEOFF):
                return fs, ()  # our own takeoff decides when it is complete
            return replace(fs, airborne=airborne), ()
        case Disarmed(mode, stalled):
            return _disarmed(fs, mode, stalled)
        case ModeReport(in_our_mode, mode, stalled):
            return _mode_report(fs, in_our_mode, mode, stalled)
        case LinkLost(timeout):
            lost = replace(fs, link_lost=True)
            said = Say("link_lost", f"MAVLink link lost (nothing from the autopilot for {timeout} s) while "
                       f"{fs.state.value}; stopped commanding (cause: the link; the companion ran)",
                       {"previous_state": fs.state.value, "cause": "link"})
            reaction = on_link(fs.state, link_ok=False)
            if reaction is None:
                return lost, (said,)
            new, acts = _to(lost, reaction[0], reaction[1], Release())
            return new, (*acts, said)
        case Stalled(reason):
            if not fs.controlling:
                return fs, ()
            return _to(fs, S.FAILSAFE, f"{reason}: stopped commanding ({fs.state.value} before); send 'start' to "
                       "take control again", Release())
        case TakingControl(reason):
            return _to(fs, S.ARMING, reason)
        case Armed(mode):
            where = "in the air" if fs.airborne else "on the ground"
            return _to(fs, S.READY, f"armed in {mode} ({where}): holding")
        case ControlTakenBack(mode):
            return _to(fs, S.READY, f"in control ({mode}): holding")
        case TakeoffBegan(reason):
            return _to(fs, S.TAKEOFF, reason)
        case TookOff(reason):
            return _to(replace(fs, airborne=True), S.READY, reason)
        case TakeoffInterrupted(reason):
            return _to(fs, S.READY, reason) if fs.state is S.TAKEOFF else (fs, ())
        case SequenceAborted(reason, armed):
            if fs.state not in (S.ARMING, S.TAKEOFF):
                return fs, ()
            return _to(fs, S.FAILSAFE if armed else S.IDLE, reason, StopStream())
        case ExitBegan(reason, flying):
            if fs.state is S.ARMING and fs.airborne and flying:
                return _to(fs, S.READY, f"{reason}: taking control back interrupted")
            return fs, ()
        case LandRequested():
            return _to(replace(fs, exit_requested=True), S.LANDING,
                       f"land command ({fs.state.value}): the autopilot lands")
        case DisarmedOnCommand(reason):
            return _to(replace(fs, airborne=False), S.IDLE, reason)
        case HandedOver(reason, mode, landing):
            return _to(fs, S.LANDING if landing else S.PILOT, f"{reason}: handed over to the autopilot ({mode})")
        case MissionStarted(mission_id):
            return _to(fs, S.STREAMING, f"flying mission {mission_id}")
        case ReplanFlown(what):
            return _to(fs, S.STREAMING, f"replanned: {what}")
        case MissionComplete(mission_id):
            if fs.state is not S.STREAMING:
                return fs, ()
            return _to(fs, S.HOLDING, f"mission {mission_id} complete: holding at the last waypoint")
        case StoppedAfterBraking():
            if fs.state is not S.BRAKING:
                return fs, ()
            return _to(fs, S.HOLDING, "stopped after braking: holding position")
        case Braking(reason):
            return _to(fs, S.BRAKING, reason)
    raise TypeError(f"not a supervisor event: {event!r}")  # pragma: no cover - mypy sees the match is total


def _disarmed(fs: FlightState, mode: str, stalled: bool) -> Step:
    """A disarmed vehicle flies nothing, whatever mode it reports (PX4 reports OFFBOARD while
    disarmed after an offboard landing): checked before the mode."""
    down = replace(fs, airborne=False)
    if fs.state in IN_OUR_MODE and not fs.disarm_requested:
        after = " after the companion stalled" if stalled else ""
        new, acts = _to(down, S.IDLE, f"the autopilot disarmed the vehicle{after}", Release())
        return new, (*acts, Say("failsafe", f"the autopilot disarmed the vehicle{after} (mode {mode})",
                                {"mode": mode, "cause": "companion" if stalled else "autopilot"}))
    if fs.state in (S.LANDING, S.PILOT, S.FAILSAFE):
        return _to(down, S.IDLE, "landed and disarmed" if fs.state is S.LANDING
                   else f"the vehicle disarmed ({fs.state.value} before): following the autopilot")
    if fs.state is S.IDLE:
        return down, ()
    return fs, ()  # ours, and we asked for the disarm: the command itself says so


def _mode_report(fs: FlightState, in_our_mode: bool, mode: str, stalled: bool) -> Step:
    """Leaving our mode without our request stops commanding at once: a pilot took over, or,
    while the companion was stalled, the autopilot's offboard-loss failsafe set off by our own
    silence."""
    reaction = on_mode_report(fs.state, in_our_mode, fs.exit_requested)
    if reaction is None:
        return fs, ()
    if stalled:
        new, acts = _to(fs, S.FAILSAFE, f"the autopilot left OFFBOARD/GUIDED for {mode} while the companion "
                        "was stalled (no setpoints)", Release())
        return new, (*acts, Say("failsafe", f"the autopilot switched to {mode} while the companion was stalled: "
                                "stopped commanding; send 'start' to take control again",
                                {"mode": mode, "cause": "companion"}))
    new, acts = _to(fs, reaction[0], f"{reaction[1]} (mode {mode})", Release())
    return new, (*acts, Say("pilot_takeover", f"autopilot switched to {mode}: stopped commanding; send 'start' "
                            "to take control again", {"mode": mode}))


def _nothing() -> None:
    pass


def _unobserved(_before: FlightState, _event: Event, _after: FlightState, _actions: tuple[Action, ...]) -> None:
    pass


class Supervisor:
    """Holds the current `FlightState`, the only object that replaces it (`handle`), and
    carries out the actions `transition` returns through the sinks connected to it."""

    def __init__(self, initial: FlightState | None = None) -> None:
        self._now = initial if initial is not None else FlightState()
        self.history: list[dict[str, Any]] = []  # every transition, as published
        self._announce: Callable[[Announce], None] = lambda _a: None
        self._say: Callable[[Say], None] = lambda _a: None
        self._release: Callable[[], None] = _nothing
        self._stop_stream: Callable[[], None] = _nothing
        self._observe: Observer = _unobserved

    def connect(self, *, announce: Callable[[Announce], None] | None = None, say: Callable[[Say], None] | None = None,
                release: Callable[[], None] | None = None, stop_stream: Callable[[], None] | None = None,
                observe: Observer | None = None) -> None:
        """Where the actions go (the reporter, the control), and who is shown every `handle`
        call (the recorder's tap: it must return at once): the shell wires them once."""
        self._announce = announce or self._announce
        self._say = say or self._say
        self._release = release or self._release
        self._stop_stream = stop_stream or self._stop_stream
        self._observe = observe or self._observe

    def handle(self, event: Event) -> tuple[Action, ...]:
        """Apply `event`, then carry out its actions in order (the new state is in place
        before any of them runs, as each published event carries it)."""
        before = self._now
        self._now, actions = transition(before, event)
        # shown before the actions run: an action may lead to another `handle` call, and the
        # observer must see the calls in the order the states replaced each other (replay
        # checks that each one starts from the last one's end)
        try:
            self._observe(before, event, self._now, actions)
        except Exception:  # a recorder's fault must never keep a Release from being carried out
            log.exception("supervisor: the transition observer failed")
        for action in actions:
            match action:
                case Announce(src, dst, reason):
                    self.history.append({"type": "state", "from": src.value, "to": dst.value, "message": reason})
                    self._announce(action)
                case Release():
                    self._release()
                case StopStream():
                    self._stop_stream()
                case Say():
                    self._say(action)
        return actions

    # -- read-only views ---------------------------------------------------------------------

    @property
    def value(self) -> FlightState:
        return self._now

    @property
    def state(self) -> State:
        return self._now.state

    @property
    def airborne(self) -> bool:
        return self._now.airborne

    @property
    def seen_link(self) -> bool:
        return self._now.seen_link

    @property
    def link_lost(self) -> bool:
        return self._now.link_lost

    @property
    def exit_requested(self) -> bool:
        return self._now.exit_requested

    @property
    def disarm_requested(self) -> bool:
        return self._now.disarm_requested

    @property
    def starting(self) -> bool:
        return self._now.starting

    @property
    def ground_z(self) -> float | None:
        return self._now.ground_z

    @property
    def controlling(self) -> bool:
        return self._now.controlling

    @property
    def flying_ours(self) -> bool:
        return self._now.flying_ours

    def can(self, to: State) -> bool:
        return self._now.can(to)

    def refuse(self, command: str, *, armed: bool, auto_arm: bool, has_mission: bool,
               reported_in_air: bool = False) -> str | None:
        return self._now.refuse(command, armed=armed, auto_arm=auto_arm, has_mission=has_mission,
                                reported_in_air=reported_in_air)
