"""The flight state machine: the vehicle's situation as the companion sees it, in one place.

Pure logic, no sockets, no clock. `FlightState` holds the state and every flag about the
vehicle's situation (airborne, link lost/seen, an exit or a disarm we asked for, a `start`
in progress) as one frozen value; `companion/supervisor.py` is the only place that makes a
new one, from events; the rest of the service reads it and submits events, never keeps a copy.

States (README, "State machine"):
IDLE -> ARMING -> TAKEOFF -> READY -> STREAMING -> HOLDING, plus
PILOT (someone else took control), BRAKING (stopping inside a free corridor),
FAILSAFE (the autopilot left our mode on its own, or the link was lost) and
LANDING (the autopilot lands at our request).

READY means "in our mode and holding": on the ground (armed, not yet taken off) or in
the air; `airborne` says which. Every transition is returned as an event dict with its
reason (`go`); an illegal transition raises, so a bug shows as an error instead of a silent jump.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, replace
from typing import Any


class State(enum.Enum):
    IDLE = "IDLE"
    ARMING = "ARMING"
    TAKEOFF = "TAKEOFF"
    READY = "READY"
    STREAMING = "STREAMING"
    HOLDING = "HOLDING"
    BRAKING = "BRAKING"
    LANDING = "LANDING"
    PILOT = "PILOT"
    FAILSAFE = "FAILSAFE"


S = State
_ANY_EXIT = {S.IDLE, S.PILOT, S.FAILSAFE}
ALLOWED: dict[State, set[State]] = {
    # IDLE -> LANDING: a restart that finds the vehicle in the air can still land it.
    S.IDLE: {S.ARMING, S.PILOT, S.FAILSAFE, S.LANDING},
    S.ARMING: {S.TAKEOFF, S.READY, S.LANDING} | _ANY_EXIT,
    S.TAKEOFF: {S.READY, S.HOLDING, S.LANDING} | _ANY_EXIT,
    S.READY: {S.TAKEOFF, S.STREAMING, S.HOLDING, S.BRAKING, S.LANDING} | _ANY_EXIT,
    S.STREAMING: {S.HOLDING, S.BRAKING, S.LANDING} | _ANY_EXIT,
    S.HOLDING: {S.TAKEOFF, S.STREAMING, S.BRAKING, S.LANDING} | _ANY_EXIT,
    S.BRAKING: {S.HOLDING, S.STREAMING, S.LANDING} | _ANY_EXIT,
    S.LANDING: _ANY_EXIT,
    S.PILOT: {S.ARMING, S.FAILSAFE, S.IDLE, S.LANDING},
    S.FAILSAFE: {S.ARMING, S.PILOT, S.IDLE, S.LANDING},
}

# States in which the companion commands the vehicle with setpoints.
CONTROLLING = frozenset({S.ARMING, S.TAKEOFF, S.READY, S.STREAMING, S.HOLDING, S.BRAKING})
# States in which the vehicle is in our mode (OFFBOARD/GUIDED) by our request.
IN_OUR_MODE = frozenset({S.TAKEOFF, S.READY, S.STREAMING, S.HOLDING, S.BRAKING})
# States in which we hold or fly a plan; with `airborne`, a mission may be flown.
HOLDING_CONTROL = frozenset({S.READY, S.STREAMING, S.HOLDING, S.BRAKING})


class IllegalTransition(RuntimeError):
    pass


@dataclass(frozen=True)
class FlightState:
    """The vehicle's situation as the companion sees it: one immutable value, replaced only by
    the supervisor (companion/supervisor.py), so no module can change part of it behind another's back."""

    state: State = S.IDLE
    airborne: bool = False  # the vehicle is (or may be) in the air
    seen_link: bool = False  # an autopilot heartbeat has arrived since start
    link_lost: bool = False  # no heartbeat for the link timeout (until one arrives)
    exit_requested: bool = False  # we asked the autopilot to leave our mode (land)
    disarm_requested: bool = False  # we asked for the disarm (it is not a failsafe)
    starting: bool = False  # a `start` sequence is running (its takeoff must not fly the pending mission)
    ground_z: float | None = None  # NED z (local frame) where the vehicle last stood disarmed

    def can(self, to: State) -> bool:
        return to == self.state or to in ALLOWED[self.state]

    @property
    def controlling(self) -> bool:
        return self.state in CONTROLLING

    @property
    def flying_ours(self) -> bool:
        """In the air, in our mode, holding or flying a plan: a mission or a change may fly."""
        return self.state in HOLDING_CONTROL and self.airborne

    def refuse(self, command: str, *, armed: bool, auto_arm: bool, has_mission: bool,
               reported_in_air: bool = False) -> str | None:
        """Why `command` is refused now (None: accepted). `reported_in_air`: the autopilot's
        landed state says "in air"."""
        return refuse_command(self.state, command, armed=armed, auto_arm=auto_arm, has_mission=has_mission,
                              airborne=self.airborne or reported_in_air, reported_in_air=reported_in_air,
                              link_lost=self.link_lost)


def go(fs: FlightState, to: State, reason: str) -> tuple[FlightState, dict[str, Any] | None]:
    """`fs` moved to `to`, and the transition event (None when already there). An illegal
    transition raises: a bug shows as an error instead of a silent jump."""
    if to == fs.state:
        return fs, None
    if to not in ALLOWED[fs.state]:
        raise IllegalTransition(f"{fs.state.value} -> {to.value} ({reason})")
    event = {"type": "state", "from": fs.state.value, "to": to.value, "message": reason}
    return replace(fs, state=to), event


# Commands that take control: never begun without a link (the autopilot would not hear them, and
# a stale picture of the vehicle is no base to command it from). hold, land, abort and disarm
# are still tried: they stop or hand over, and the link may come back.
NEED_LINK = frozenset({"arm", "takeoff", "start", "resume"})


def refuse_command(state: State, command: str, *, armed: bool, auto_arm: bool, has_mission: bool,
                   airborne: bool = False, reported_in_air: bool = False, link_lost: bool = False) -> str | None:
    """Why `command` is refused in `state` (None: accepted). The table is in the README."""
    if link_lost and command in NEED_LINK:
        return ("the MAVLink link to the autopilot is lost (no heartbeat within [mavlink] link_timeout): nothing "
                "takes control until it is back")
    if command == "arm":
        if armed and state in CONTROLLING:
            return "already armed and in control"
        if state in (S.ARMING, S.TAKEOFF, S.LANDING):
            return f"busy ({state.value})"
        return None
    if command == "takeoff":
        if not armed and not auto_arm:
            return "vehicle is disarmed; send 'arm' first (auto_arm is off)"
        if state in (S.STREAMING, S.BRAKING, S.LANDING, S.TAKEOFF):
            return f"cannot take off while {state.value}"
        return None
    if command == "start":
        # From PILOT/FAILSAFE (or IDLE with the vehicle in the air, after a restart),
        # `start` without a mission takes control back and holds.
        takes_back = state in (S.PILOT, S.FAILSAFE) or (state is S.IDLE and armed and airborne)
        if not has_mission and not takes_back:
            return "no mission loaded"
        if not armed and not auto_arm:
            return "vehicle is disarmed; send 'arm' and 'takeoff' first (auto_arm is off)"
        if state in (S.ARMING, S.TAKEOFF, S.LANDING):
            return f"busy ({state.value})"
        return None
    if command == "hold":
        if state not in HOLDING_CONTROL or not airborne:
            return f"not flying under our control ({state.value}{'' if airborne else ', on the ground'})"
        return None
    if command == "resume":
        if state not in HOLDING_CONTROL or not airborne:
            return f"not flying under our control ({state.value}{'' if airborne else ', on the ground'})"
        if not has_mission:
            return "no mission to resume"
        return None
    if command == "land":
        if state is S.LANDING:
            return "already landing"
        if not armed:
            return "vehicle is disarmed (on the ground)"
        return None
    if command == "abort":
        return None
    if command == "disarm":
        if not armed:
            return "already disarmed"
        if reported_in_air:
            return "vehicle is in the air (land first)"
        return None
    return f"unknown command {command!r}"


def on_mode_report(state: State, in_our_mode: bool, requested_exit: bool) -> tuple[State, str] | None:
    """React to the autopilot's reported mode.

    Leaving OFFBOARD/GUIDED while we are in control and did not ask for it is a
    pilot takeover: stop commanding at once and never retake control without a
    new `start`.
    """
    if state in IN_OUR_MODE and not in_our_mode and not requested_exit:
        return S.PILOT, "autopilot left the offboard/guided mode without our request"
    return None


def on_link(state: State, link_ok: bool) -> tuple[State, str] | None:
    if not link_ok and state in CONTROLLING:
        return S.FAILSAFE, "MAVLink link lost: no autopilot heartbeat"
    return None
