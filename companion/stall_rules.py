"""What the companion does about its own stall: one pure function.

`stall_step(rules, state, observation) -> (state, action)` decides, at each beat of the event
loop (companion/stalls.py `StallWatch.loop_liveness`), whether the companion stalled (the loop
did not run for `[setpoints] loop_stall_limit`, or the setpoint sender withheld setpoints because
it saw the loop, or itself, stall) and what follows: not in control, nothing to do; setpoints
silent for at least STALL_HOLD_WITHIN, release control (the autopilot may have left OFFBOARD on
its own); else hold. It also remembers the flight state before the stall, which the `stalled`
event names. No I/O, no clock, no asyncio: the watch reads the pulse and the sender's latch,
calls this, shows the call to the flight recorder (/stalls/step) and carries the action out
(the hand-over's release or hold, the latch's release, the event). `python -m companion replay`
runs each recorded call again (companion/replay_stalls.py).
"""

from __future__ import annotations

from dataclasses import dataclass

# s: setpoints withheld after a stall for less than this (half PX4's default COM_OF_LOSS_T):
# the autopilot still flies our plan, so the companion keeps control and holds
STALL_HOLD_WITHIN = 0.5

THREAD = "the setpoint thread"
LOOP = "its event loop"


@dataclass(frozen=True)
class StallRules:
    limit: float  # s: [setpoints] loop_stall_limit
    hold_within: float = STALL_HOLD_WITHIN


@dataclass(frozen=True)
class StallState:
    was: str = ""  # the flight state before any stall (the supervisor's state value)


@dataclass(frozen=True)
class Settled:
    """The watch starts, or a stall was dealt with: the flight state now."""

    state: str


@dataclass(frozen=True)
class Beat:
    """One beat of the loop: the time since the one before, the sender's latch (who withheld:
    "loop" or "thread", None: nothing withheld; the stall it measured), the time since a
    setpoint last left, whether the companion controls the vehicle, the flight state now."""

    gap: float
    withheld_by: str | None
    withheld_stall: float
    silence: float
    controlling: bool
    state: str


Observation = Settled | Beat


@dataclass(frozen=True)
class Quiet:
    """Nothing stalled."""


@dataclass(frozen=True)
class Stalled:
    """The companion stalled: `what` did not run for `stall` s; `reaction` "none" (not in
    control), "release" (control released) or "hold"; then release the sender's latch and say
    so (`was`: the flight state before; `withheld`, `silence`: setpoints withheld and for how
    long)."""

    what: str
    stall: float
    reason: str
    reaction: str
    was: str
    withheld: bool
    silence: float


Action = Quiet | Stalled
Step = tuple[StallState, Action]


def stall_step(rules: StallRules, state: StallState, seen: Observation) -> Step:
    if isinstance(seen, Settled):
        return StallState(seen.state), Quiet()
    withheld = seen.withheld_by is not None
    if seen.gap <= rules.limit and not withheld:
        return StallState(seen.state), Quiet()  # as it was before any stall
    what = THREAD if seen.withheld_by == "thread" else LOOP
    stall = max(seen.gap, seen.withheld_stall if withheld else 0.0)
    reason = f"the companion stalled ({what} did not run for {stall * 1000:.0f} ms)"
    if not seen.controlling:
        reaction = "none"
    elif withheld and seen.silence >= rules.hold_within:
        reaction = "release"
    else:
        reaction = "hold"
    return state, Stalled(what, stall, reason, reaction, state.was, withheld, seen.silence)
