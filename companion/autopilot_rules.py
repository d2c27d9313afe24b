"""How what the autopilot reports becomes supervisor events: one pure function.

`watch_step(rules, state, flight, reading, now) -> (state, outputs)` decides, for one MAVLink message
the autopilot watch reacts to (a heartbeat, a position, the landed state, a STATUSTEXT or an
EVENT) or one of its timer checks (the link), which supervisor events it makes and what the
watch must remember for the next one. No sockets, no clock (`now` is an input), no callbacks:
companion/autopilot.py (`AutopilotWatch`) reads the link's state into a typed reading, calls
this, hands the supervisor events to `Supervisor.handle` in order and carries out the rest
(telemetry requests, the `link` and `autopilot` events). The flight recorder records every call
on /autopilot/step and `python -m companion replay` runs each one again (companion/replay_autopilot.py).

`flight` is the supervisor's state when the reading arrived: the rules read it (whether the link
was seen or lost, the ground learnt, whether the vehicle is airborne, our own takeoff) and never
write it; the supervisor's `transition` decides what each event does to it.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace
from typing import Any

import numpy as np

from companion.config import Config
from companion.flight import FlightState, State
from companion.supervisor import (
    Disarmed,
    GroundLearnt,
    Heartbeat,
    HeightReport,
    LandedStateReport,
    LinkLost,
    ModeReport,
)
from companion.wire.vehicle import (
    MAV_LANDED_IN_AIR,
    MAV_LANDED_LANDING,
    MAV_LANDED_ON_GROUND,
    follow_mode,
    heard,
)

# Where the autopilot sends no landed state (EXTENDED_SYS_STATE), `airborne` follows the
# height above where the vehicle stood disarmed, and the speed.
LANDED_STATE_STALE = 3.0  # s without EXTENDED_SYS_STATE: the landed state is unknown
AIR_HEIGHT = 0.5  # m above the ground: in the air
GROUND_HEIGHT = 0.3  # m: on the ground when also at rest ...
GROUND_SPEED = 0.2  # m/s
GROUND_FOR = 1.0  # ... for this long


_NAMES: dict[type, tuple[str, ...]] = {}


def _names(kind: type) -> tuple[str, ...]:
    names = _NAMES.get(kind)
    if names is None:
        names = _NAMES[kind] = tuple(f.name for f in fields(kind))
    return names


class _Compact:
    """Pickled as its class and its fields in order, without their names: half the bytes of a
    data class's own pickle, in records written tens of times a second (/autopilot/step)."""

    def __reduce__(self) -> tuple[Any, tuple[Any, ...]]:
        return type(self), tuple(getattr(self, n) for n in _names(type(self)))


@dataclass(frozen=True)
class WatchRules(_Compact):
    """The configuration the rules use (from [vehicle] and [mavlink]; the recording's
    configuration gives it to replay)."""

    sysid: int = 1  # [vehicle] sysid: the autopilot's system
    compid: int = 1  # [vehicle] autopilot_component
    link_timeout: float = 3.0  # [mavlink] link_timeout, s

    @staticmethod
    def of(cfg: Config) -> WatchRules:
        return WatchRules(cfg.vehicle.sysid, cfg.vehicle.autopilot_component, cfg.mavlink.link_timeout)


@dataclass(frozen=True)
class WatchState(_Compact):
    """What the watch remembers between readings."""

    # since when the vehicle has been at rest near the ground (height rule; inf: it is not)
    on_ground_since: float = math.inf
    lost_at: float = -math.inf  # when the link was declared lost (for the silence said at restore)
    event_seq: int | None = None  # the last PX4 EVENT sequence relayed (a resent one is not)


# -- readings: the fields of a message (and the link's state) the rules use ------------------


@dataclass(frozen=True)
class HeartbeatSeen(_Compact):
    """The autopilot's heartbeat, as the link decoded it."""

    autopilot: str | None  # "px4" | "ardupilot"
    mode: str
    armed: bool
    stalled: bool  # the companion is stalled or just woke from a stall (companion/stalls.py)
    sysid: int
    compid: int
    # the heartbeat's MAV_AUTOPILOT, MAV_TYPE, base_mode and custom_mode as received, which
    # autopilot, mode and armed were read from (companion.wire.vehicle.read_heartbeat); the rules
    # do not use it, replay reads it again. None: not known (a reading built without a message)
    wire: tuple[int, int, int, int] | None = None


@dataclass(frozen=True)
class PositionSeen(_Compact):
    """LOCAL_POSITION_NED, with the link's armed state and when EXTENDED_SYS_STATE last came."""

    x: float
    y: float
    z: float
    vx: float
    vy: float
    vz: float
    armed: bool
    landed_at: float  # monotonic s; -inf: never
    sysid: int
    compid: int


@dataclass(frozen=True)
class LandedStateSeen(_Compact):
    """EXTENDED_SYS_STATE's landed_state (MAV_LANDED_STATE)."""

    landed_state: int
    sysid: int
    compid: int


@dataclass(frozen=True)
class NoteSeen(_Compact):
    """A STATUSTEXT, or a PX4 EVENT with its sequence number."""

    kind: str  # "STATUSTEXT" | "EVENT"
    sequence: int | None
    sysid: int
    compid: int


@dataclass(frozen=True)
class LinkCheck(_Compact):
    """The link's timer check (the heartbeat and telemetry loops): when the autopilot was last heard."""

    last_heartbeat: float  # -inf: never
    last_message: float
    stalled: bool


Reading = HeartbeatSeen | PositionSeen | LandedStateSeen | NoteSeen | LinkCheck

# -- outputs besides the supervisor's events: what the watch itself does about them -----------


@dataclass(frozen=True)
class LinkFound(_Compact):
    """The first heartbeat: say so, ask for telemetry, read the autopilot's limits."""

    autopilot: str | None
    mode: str


@dataclass(frozen=True)
class LinkRestored(_Compact):
    """A heartbeat after the link was declared lost (the autopilot may have rebooted)."""

    silence_s: float  # about how long nothing was heard
    mode: str
    armed: bool


@dataclass(frozen=True)
class Relay(_Compact):
    """Relay the autopilot's last note as an `autopilot` event."""

    kind: str


WatchEvent = Heartbeat | Disarmed | ModeReport | GroundLearnt | HeightReport | LandedStateReport | LinkLost
Output = WatchEvent | LinkFound | LinkRestored | Relay
Step = tuple[WatchState, tuple[Output, ...]]
WATCH_EVENTS = (Heartbeat, Disarmed, ModeReport, GroundLearnt, HeightReport, LandedStateReport, LinkLost)


def watch_step(rules: WatchRules, ws: WatchState, flight: FlightState, reading: Reading, now: float) -> Step:
    """The watch's new state and what to do for `reading` at monotonic `now`, in order. A
    message from another system or component than the autopilot's makes nothing."""
    if not isinstance(reading, LinkCheck) and (reading.sysid, reading.compid) != (rules.sysid, rules.compid):
        return ws, ()
    match reading:
        case HeartbeatSeen():
            return _heartbeat(rules, ws, flight, reading, now)
        case PositionSeen():
            return _position(ws, flight, reading, now)
        case LandedStateSeen(landed):
            return ws, (LandedStateReport(in_air=landed in (MAV_LANDED_IN_AIR, MAV_LANDED_LANDING),
                                          on_ground=landed == MAV_LANDED_ON_GROUND),)
        case NoteSeen(kind, sequence):
            if kind != "EVENT":
                return ws, (Relay(kind),)
            if sequence == ws.event_seq:  # a resent event
                return ws, ()
            return replace(ws, event_seq=sequence), (Relay(kind),)
        case LinkCheck(last_heartbeat, last_message, stalled):
            if not flight.seen_link or flight.link_lost or heard(last_heartbeat, last_message, rules.link_timeout, now):
                return ws, ()
            if stalled:
                # Silence seen by a loop that did not run says nothing about the link: what the
                # autopilot sent meanwhile waits in the socket and is read first.
                return ws, ()
            return replace(ws, lost_at=now), (LinkLost(rules.link_timeout),)
    raise TypeError(f"not a watch reading: {reading!r}")  # pragma: no cover - mypy sees the match is total


def _heartbeat(rules: WatchRules, ws: WatchState, flight: FlightState, hb: HeartbeatSeen, now: float) -> Step:
    out: list[Output] = [Heartbeat()]
    if not flight.seen_link:
        out.append(LinkFound(hb.autopilot, hb.mode))
    if flight.link_lost:
        out.append(LinkRestored(now - ws.lost_at + rules.link_timeout, hb.mode, hb.armed))
    # Armed state first: a disarmed vehicle flies nothing, whatever mode it reports (the
    # supervisor decides what each means); while the companion itself is stalled (or just woke
    # from a stall), what the autopilot did meanwhile is put down to that stall.
    if not hb.armed:
        out.append(Disarmed(hb.mode, hb.stalled))
    else:
        out.append(ModeReport(follow_mode(hb.autopilot, hb.mode), hb.mode, hb.stalled))
    return ws, tuple(out)


def _position(ws: WatchState, flight: FlightState, p: PositionSeen, now: float) -> Step:
    """`airborne` from height and speed, while the autopilot sends no landed state."""
    if not all(math.isfinite(v) for v in (p.x, p.y, p.z)):
        return ws, ()
    if not p.armed:
        return _since(ws, math.inf), (GroundLearnt(p.z),)
    if now - p.landed_at < LANDED_STATE_STALE or flight.ground_z is None:
        return ws, ()
    if flight.state in (State.ARMING, State.TAKEOFF):
        return ws, ()  # our own takeoff decides when it is complete
    height = flight.ground_z - p.z
    if height > AIR_HEIGHT:
        return _since(ws, math.inf), (() if flight.airborne else (HeightReport(airborne=True),))
    if height < GROUND_HEIGHT and float(np.linalg.norm((p.vx, p.vy, p.vz))) < GROUND_SPEED:
        since = min(ws.on_ground_since, now)
        landed = flight.airborne and now - since >= GROUND_FOR
        return _since(ws, since), ((HeightReport(airborne=False),) if landed else ())
    return _since(ws, math.inf), ()


def _since(ws: WatchState, t: float) -> WatchState:
    # the same value, not a copy, when nothing changes (most positions): 30 calls a second
    return ws if ws.on_ground_since == t else replace(ws, on_ground_since=t)
