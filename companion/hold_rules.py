"""Whether the autopilot holds the vehicle after a hand-over: one pure function.

`hold_step(rules, state, observation) -> (state, action)` watches the vehicle after the
companion handed it to an autonomous hold (companion/handover.py `HandOver._confirm_hold`): from
where the hold began (`Began`: the time, the altitude, the mode, when the verified stop before it
has settled) and each sample of the vehicle (`Seen`: the time, armed, the mode, the altitude, the
velocity) it decides to watch on (`Watch`), that the hold is confirmed (`Holds`: the mode stayed,
the vehicle armed, its altitude within `altitude_tolerance` of where the hold began throughout,
and, once settled, its speed under `speed_tolerance`, for `confirm` s), or that it is not
(`Fails`, with the problem). "Settled": its speed once under the tolerance, or `settle` s after
the verified stop's end. A hand-over is confirmed by watching the vehicle, not only its mode.
No I/O, no clock, no asyncio: the hand-over samples the link's state, calls this, shows the call
to the flight recorder (/handover/hold) and says the verdict; `python -m companion replay` runs
each recorded call again (companion/replay_hold.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

POLL = 0.05  # s between samples


@dataclass(frozen=True)
class HoldRules:
    """The autopilot's hold profile's thresholds (companion.handover.hold_profile)."""

    altitude_tolerance: float
    speed_tolerance: float
    settle: float
    confirm: float


@dataclass(frozen=True)
class HoldState:
    mode: str = ""  # the mode the hold began in
    z0: float = 0.0  # m, NED: the altitude where it began
    start: float = 0.0  # the loop's time when it began
    settle_by: float = 0.0  # the speed is judged from then on at the latest
    done_by: float = 0.0  # confirmed no earlier
    latest: float = 0.0  # watched no later (longer than `confirm` only while not settled)
    worst_dz: float = 0.0  # m: the largest altitude change (signed, NED: > 0 down)
    worst_v: float = 0.0  # m/s: the largest speed
    settled: bool = False


@dataclass(frozen=True)
class Began:
    """The hold began: now, the altitude, the mode; when the verified stop before it settles
    (None: there was none: `settle` s from now)."""

    now: float
    z: float
    mode: str
    settle_by: float | None


@dataclass(frozen=True)
class Seen:
    """A sample of the vehicle: now, armed, the mode, the altitude (NED z), the velocity."""

    now: float
    armed: bool
    mode: str
    z: float
    velocity: tuple[float, float, float]


Observation = Began | Seen


@dataclass(frozen=True)
class Watch:
    """Sample again after `seconds`."""

    seconds: float = POLL


@dataclass(frozen=True)
class Holds:
    """Confirmed after `watched` s."""

    watched: float


@dataclass(frozen=True)
class Fails:
    """Not held: `problem`, after `watched` s."""

    problem: str
    watched: float


Action = Watch | Holds | Fails
Step = tuple[HoldState, Action]


def _next(state: HoldState, now: float) -> Action:
    if now < state.latest and not (state.settled and now >= state.done_by):
        return Watch(POLL)
    return Holds(round(now - state.start, 2))


def hold_step(rules: HoldRules, state: HoldState, seen: Observation) -> Step:
    if isinstance(seen, Began):
        start = seen.now
        settle_by = seen.settle_by if seen.settle_by is not None else start + rules.settle
        # `confirm` s, longer only while the vehicle has not settled (then up to 1 s past the settle time)
        begun = HoldState(seen.mode, seen.z, start, settle_by, start + rules.confirm,
                          max(start + rules.confirm, min(settle_by, start + rules.settle) + 1.0))
        return begun, _next(begun, start)
    dz = seen.z - state.z0
    speed = float(np.linalg.norm(np.asarray(seen.velocity, dtype=float)))
    now = HoldState(state.mode, state.z0, state.start, state.settle_by, state.done_by, state.latest,
                    dz if abs(dz) > abs(state.worst_dz) else state.worst_dz, max(state.worst_v, speed),
                    state.settled or speed <= rules.speed_tolerance or seen.now >= state.settle_by)
    problem = None
    if not seen.armed:
        problem = "the vehicle disarmed"
    elif seen.mode != state.mode:
        problem = f"the autopilot left {state.mode} for {seen.mode}"
    elif abs(dz) > rules.altitude_tolerance:
        problem = f"the vehicle {'descends' if dz > 0 else 'climbs'}: {abs(dz):.2f} m from where the hold began"
    elif now.settled and speed > rules.speed_tolerance:
        vz = float(seen.velocity[2])
        how = f" ({'descending' if vz > 0 else 'climbing'} at {abs(vz):.2f} m/s)" if abs(vz) >= 0.5 * speed else ""
        problem = f"the vehicle moves at {speed:.2f} m/s{how}"
    if problem is not None:
        return now, Fails(problem, round(seen.now - state.start, 2))
    return now, _next(now, seen.now)
