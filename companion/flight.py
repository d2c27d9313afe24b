"""The flight state machine: pure logic, no sockets, no clock.

States (see the README, "State machine", for the diagram):
IDLE -> ARMING -> TAKEOFF -> READY -> STREAMING -> HOLDING, plus
PILOT (someone else took control), BRAKING (no safe plan: stopping inside the
current corridor), FAILSAFE (the autopilot left our mode on its own, or the
link was lost) and LANDING (the autopilot lands at our request).

Every transition is returned as an event dict with its reason; illegal
transitions raise, so a bug shows up as an error instead of a silent jump.
"""

from __future__ import annotations

import enum
from dataclasses import dataclass, field
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
    S.IDLE: {S.ARMING, S.PILOT, S.FAILSAFE},
    S.ARMING: {S.TAKEOFF, S.READY} | _ANY_EXIT,
    S.TAKEOFF: {S.READY, S.HOLDING, S.LANDING} | _ANY_EXIT,
    S.READY: {S.TAKEOFF, S.STREAMING, S.HOLDING, S.LANDING} | _ANY_EXIT,
    S.STREAMING: {S.HOLDING, S.BRAKING, S.LANDING} | _ANY_EXIT,
    S.HOLDING: {S.TAKEOFF, S.STREAMING, S.BRAKING, S.LANDING} | _ANY_EXIT,
    S.BRAKING: {S.HOLDING, S.STREAMING, S.LANDING} | _ANY_EXIT,
    S.LANDING: _ANY_EXIT,
    S.PILOT: {S.ARMING, S.FAILSAFE, S.IDLE},
    S.FAILSAFE: {S.ARMING, S.PILOT, S.IDLE},
}

# States in which the companion commands the vehicle with setpoints.
CONTROLLING = frozenset({S.ARMING, S.TAKEOFF, S.READY, S.STREAMING, S.HOLDING, S.BRAKING})
# States in which the vehicle is in our mode (OFFBOARD/GUIDED) by our request.
IN_OUR_MODE = frozenset({S.TAKEOFF, S.READY, S.STREAMING, S.HOLDING, S.BRAKING})
AIRBORNE_CONTROL = frozenset({S.READY, S.STREAMING, S.HOLDING, S.BRAKING})


class IllegalTransition(RuntimeError):
    pass


@dataclass
class Flight:
    state: State = S.IDLE
    history: list[dict[str, Any]] = field(default_factory=list)

    def can(self, to: State) -> bool:
        return to == self.state or to in ALLOWED[self.state]

    def go(self, to: State, reason: str) -> dict[str, Any] | None:
        """Move to `to`; returns the transition event, None when already there."""
        if to == self.state:
            return None
        if to not in ALLOWED[self.state]:
            raise IllegalTransition(f"{self.state.value} -> {to.value} ({reason})")
        event = {"type": "state", "from": self.state.value, "to": to.value, "message": reason}
        self.state = to
        self.history.append(event)
        return event

    @property
    def controlling(self) -> bool:
        return self.state in CONTROLLING


def refuse_command(state: State, command: str, *, armed: bool, auto_arm: bool, has_mission: bool) -> str | None:
    """Why `command` is refused in `state` (None: accepted)."""
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
        if not has_mission and state not in (S.PILOT, S.FAILSAFE):
            # From PILOT/FAILSAFE, `start` without a mission takes control back and holds.
            return "no mission loaded"
        if not armed and not auto_arm:
            return "vehicle is disarmed; send 'arm' and 'takeoff' first (auto_arm is off)"
        if state in (S.ARMING, S.TAKEOFF, S.LANDING):
            return f"busy ({state.value})"
        return None
    if command in ("hold", "resume"):
        if state not in AIRBORNE_CONTROL:
            return f"not in control ({state.value})"
        return None
    if command == "land":
        if not armed:
            return "vehicle is disarmed"
        if state in (S.LANDING, S.PILOT):
            return f"cannot land while {state.value}"
        return None
    if command == "abort":
        return None
    if command == "disarm":
        if not armed:
            return "already disarmed"
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
