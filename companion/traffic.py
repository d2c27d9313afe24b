"""The other vehicles' trajectories, as this vehicle plans against them (issue 24.3, docs/fleet.md).

Each companion with `[fleet] origin` and `[fleet] separation` > 0 publishes every plan it
proposes or commits on `<prefix>/<vehicle>/trajectory` (the message it always published, local
frame and flight time, plus a `fleet` object: the placement and time base that map it exactly
into the fleet frame on the system clock, its radius, bound speed, rank, and its separation
certificates against the neighbours it planned against, in the fleet frame). It hears the others
on `<prefix>/*/trajectory` and their liveliness on `<prefix>/*/alive`.

`Traffic` (pure bookkeeping, no I/O, times are the system clock) keeps each other vehicle's last
committed trajectory and its live proposal (until it expires or is replaced), in the fleet frame;
`neighbours` hands them to planner_core in our local frame and flight time. A vehicle whose
liveliness was lost keeps its last committed trajectory and final hold reserved, widened by its
bound speed x the time since it was lost (the neighbour's stated bound speed is raised so that
s' grows by exactly that much).
"""

from __future__ import annotations

import math
import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from companion.commit import Other, Rank
from companion.geodesy import Placement
from planner_core import FloatArray, Trajectory, hold
from planner_core.separation import (
    Neighbours,
    SeparationCertificate,
    certify_separation,
    speed_bound,
    verify_separation,
)
from planner_core.trajectory import split_at

# a clock tolerance this small stands in for 0 when a lost vehicle's widening must be paid (it is
# carried by the bound speeds: planner_core.separation.Neighbours)
WIDEN_EPS = 1e-3
# a lost vehicle's reservation stops growing after this long (s): it covers the whole site by then
WIDEN_FOR = 600.0
# how many times the commit protocol's checks may halve a common interval (planning: 4)
CHECK_DEPTH = 6


@dataclass(frozen=True)
class Claim:
    """Another vehicle's trajectory as heard: fleet frame (NED), absolute times (system clock)."""

    vehicle: str
    rank: Rank
    committed: bool
    seq: int
    trajectory: Trajectory
    radius: float
    bound_speed: float
    expires: float = math.inf  # a proposal's end of life (system clock)
    certificates: dict[str, Any] = field(default_factory=dict)


def to_fleet(traj: Trajectory, placement: Placement, time_base: float) -> Trajectory:
    """A local-frame, flight-time trajectory in the fleet frame on the system clock (exact: a
    rigid map of the control points, a shift of the knots)."""
    cp = placement.to_fleet(traj.control_points)
    return Trajectory(np.asarray(traj.times, dtype=float) + time_base, cp, None, {})


def to_local(traj: Trajectory, placement: Placement, time_base: float) -> Trajectory:
    """The inverse of `to_fleet`."""
    cp = placement.to_local(traj.control_points)
    return Trajectory(np.asarray(traj.times, dtype=float) - time_base, cp, None, {})


def from_time(traj: Trajectory, t: float) -> Trajectory:
    """What is left of a trajectory from t on (exact de Casteljau split; one that has ended by then
    holds its last point). A certificate is about the future: both sides are cut where it starts."""
    if t <= traj.times[0]:
        return traj
    if t >= traj.times[-1]:
        return hold(traj.control_points[-1, -1], t)
    cut, k = split_at(traj, t)
    return Trajectory(cut.times[k:], cut.control_points[k:], None, {})


def read_claim(body: dict[str, Any], vehicle: str) -> Claim | None:
    """Another vehicle's trajectory message (None when it carries no usable fleet part)."""
    fl = body.get("fleet")
    if not isinstance(fl, dict):
        return None
    try:
        segs = body["segments"]
        times = np.array([segs[0]["t0"], *(s["t1"] for s in segs)], dtype=float)
        cp = np.array([s["control_points"] for s in segs], dtype=float)
        if cp.ndim != 3 or cp.shape[1:] != (10, 3) or not np.all(np.isfinite(cp)) or np.any(np.diff(times) <= 0):
            return None
        placement = Placement(np.asarray(fl["offset_ned"], dtype=float), np.asarray(fl["rotation"], dtype=float))
        traj = to_fleet(Trajectory(times, cp, None, {}), placement, float(fl["time_base"]))
        return Claim(vehicle, Rank(int(fl.get("priority", 0)), vehicle), fl.get("commit") == "committed",
                     int(fl.get("seq", 0)), traj, float(fl.get("radius", 0.0)),
                     float(fl.get("bound_speed") or speed_bound(traj)),
                     float(fl.get("expires") or math.inf), dict(fl.get("certificates") or {}))
    except (KeyError, TypeError, ValueError, IndexError):
        return None


@dataclass
class Presence:
    alive: bool = True
    lost_at: float | None = None  # system clock


class Traffic:
    """The others' committed trajectories and live proposals (module docstring)."""

    def __init__(self, me: str) -> None:
        self.me = me
        self.committed: dict[str, Claim] = {}
        self.proposed: dict[str, Claim] = {}
        self.presence: dict[str, Presence] = {}

    def heard(self, claim: Claim) -> bool:
        """Keep a newly heard trajectory; False when it is older than what is held (ignored)."""
        if claim.vehicle == self.me:
            return False
        held = self.committed.get(claim.vehicle)
        if held is not None and claim.seq < held.seq:
            return False
        if claim.committed:
            self.committed[claim.vehicle] = claim
            prop = self.proposed.get(claim.vehicle)
            if prop is not None and prop.seq <= claim.seq:
                del self.proposed[claim.vehicle]
        else:
            self.proposed[claim.vehicle] = claim
        pres = self.presence.setdefault(claim.vehicle, Presence())
        pres.alive, pres.lost_at = True, None
        return True

    def liveliness(self, vehicle: str, alive: bool, now: float) -> None:
        if vehicle == self.me:
            return
        pres = self.presence.setdefault(vehicle, Presence())
        if alive:
            pres.alive, pres.lost_at = True, None
        elif pres.alive:
            pres.alive, pres.lost_at = False, now
            self.proposed.pop(vehicle, None)  # a silent vehicle commits nothing new

    def lost(self) -> list[str]:
        return sorted(v for v, p in self.presence.items() if not p.alive and v in self.committed)

    def live(self, now: float) -> list[Claim]:
        """Every trajectory to keep away from: committed ones, and proposals not yet expired."""
        for v in [v for v, c in self.proposed.items() if c.expires < now]:
            del self.proposed[v]
        return [*self.committed.values(), *self.proposed.values()]

    def widening(self, vehicle: str, now: float) -> float:
        """How far (m) a lost vehicle could have gone since it was lost (0 while alive)."""
        pres = self.presence.get(vehicle)
        if pres is None or pres.alive or pres.lost_at is None or vehicle not in self.committed:
            return 0.0
        return self.committed[vehicle].bound_speed * min(max(now - pres.lost_at, 0.0), WIDEN_FOR)

    def neighbours(self, placement: Placement, time_base: float, separation: float, clock_tolerance: float,
                   now: float, reach: float = 5.0) -> tuple[Neighbours, list[Claim]] | None:
        """The live trajectories as planner_core's `Neighbours` in our local frame and flight time
        (None when there are none); the claims in the same order."""
        claims = self.live(now)
        if not claims:
            return None
        widen = [self.widening(c.vehicle, now) for c in claims]
        eps = clock_tolerance if clock_tolerance > 0.0 or not any(widen) else WIDEN_EPS
        speeds = tuple(c.bound_speed + w / eps if eps > 0.0 else c.bound_speed for c, w in zip(claims, widen, strict=True))
        trajs = tuple(to_local(c.trajectory, placement, time_base) for c in claims)
        return Neighbours(trajs, separation, eps, speeds=speeds, reach=reach), claims

    def check(self, ours: Trajectory, placement: Placement, time_base: float, separation: float,
              clock_tolerance: float, our_speed: float, now: float,
              only: list[Claim] | None = None) -> list[tuple[Claim, SeparationCertificate | None, str]]:
        """Certify our (local, flight-time) trajectory against each live claim (or `only` these):
        (claim, certificate in the fleet frame or None, why not)."""
        mine = from_time(to_fleet(ours, placement, time_base), now)
        out: list[tuple[Claim, SeparationCertificate | None, str]] = []
        for c in (self.live(now) if only is None else only):
            w = self.widening(c.vehicle, now)
            eps = clock_tolerance if clock_tolerance > 0.0 or w == 0.0 else WIDEN_EPS
            theirs = c.bound_speed + (w / eps if eps > 0.0 else 0.0)
            # the best plane on every interval, halved deeper than planning does: a conflict here
            # makes a vehicle lose or replan, so it must not come from a coarse partition
            chk = certify_separation(mine, from_time(c.trajectory, now), separation, clock_tolerance=eps,
                                     speeds=(our_speed, theirs) if eps > 0.0 else None, exact=True,
                                     max_depth=CHECK_DEPTH)
            out.append((c, chk.certificate if chk.ok else None, "" if chk.ok else chk.message))
        return out

    def verify_theirs(self, claim: Claim, ours: Trajectory | None, our_seq: int) -> str | None:
        """Check the certificate a neighbour published against our trajectory (fleet frame) when it
        was made against the one we still fly; a sentence when it does not hold."""
        entry = claim.certificates.get(self.me)
        if ours is None or not isinstance(entry, dict) or entry.get("seq") != our_seq:
            return None
        try:
            cert = SeparationCertificate.from_dict(entry["certificate"])
        except (KeyError, TypeError, ValueError):
            return f"{claim.vehicle}'s certificate against us is malformed"
        if cert.times.size == 0:
            return f"{claim.vehicle}'s certificate against us is empty"
        start = float(cert.times[0])
        chk = verify_separation(from_time(claim.trajectory, start), from_time(ours, start), cert)
        return None if chk.ok else f"{claim.vehicle}'s certificate against our trajectory fails: {chk.message}"


def named_neighbours(text: str, names: Sequence[str]) -> str:
    """planner_core's "neighbour k" in a message as the vehicle it is (`names[k]`)."""
    def name(m: re.Match[str]) -> str:
        k = int(m.group(1))
        return names[k] if 0 <= k < len(names) else m.group(0)

    return re.sub(r"neighbour (\d+)", name, text)


def other(claim: Claim, conflicts: bool, conflicts_committed: bool = False) -> Other:
    return Other(claim.rank, claim.committed, conflicts, conflicts_committed)


def as_points(traj: Trajectory, t: FloatArray) -> FloatArray:
    """Positions at times t (held before the start and after the end)."""
    tt = np.clip(np.asarray(t, dtype=float), traj.times[0], traj.times[-1])
    return np.asarray([traj.evaluate(float(x)) for x in tt], dtype=float)
