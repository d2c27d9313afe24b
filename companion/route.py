"""A route (the waypoints being flown, their times and mission labels, the verified plan) and how
one is planned: corridors against the known obstacles, plan, verify.

Pure (no asyncio, no I/O). NED, in the flight's time base. A route's labels say which
mission waypoint each of its waypoints is: -1 for a synthetic one the companion placed (the
split point of a replan, a detour point), KNOT (-2) for one the planner's fastest allocation
placed on a long leg (a replan that allocates again drops them: the planner places its own).
"""

from __future__ import annotations

import enum
import re
import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from companion.config import Config
from companion.obstacles import Known, as_known, blocked_text, waypoint_name
from companion.wire.frames import fmt_box, fmt_point
from companion.wire.messages import MissionSpec
from planner_core import (
    Bounds,
    CorridorError,
    FloatArray,
    Polytope,
    Problem,
    Trajectory,
    allocate_times,
    plan_mission,
    shifted,
)
from planner_core import build_corridors as _build_corridors


def allocate_durations(waypoints: FloatArray, bounds: Bounds, initial_velocity: FloatArray | None = None) -> FloatArray:
    """Segment durations for `waypoints` (planner_core.allocate_times)."""
    times = allocate_times(waypoints, bounds, t0=0.0, initial_velocity=initial_velocity)
    return np.asarray(np.diff(times), dtype=float)


def build_corridors(waypoints: FloatArray, obstacles: Sequence[Polytope], mission: MissionSpec) -> tuple[Polytope, ...]:
    return tuple(_build_corridors(waypoints, list(obstacles), mission.corridor_map, mission.radius))



KNOT = -2.0


@dataclass(frozen=True)
class Route:
    mission: MissionSpec
    waypoints: FloatArray  # (k, 3)
    times: FloatArray  # (k,)
    labels: FloatArray  # (k,) mission index per waypoint, -1 synthetic
    problem: Problem
    trajectory: Trajectory  # starts at times[0]

    @property
    def t_end(self) -> float:
        return float(self.trajectory.t_end)

    def shifted(self, dt: float) -> Route:
        """The same route `dt` s later (planner_core.shifted): for a plan from a hold that came
        back after its split, which starts as well from the hold later. Not in a fleet: the
        separation from the others depends on the time."""
        return replace(self, times=self.times + dt, problem=replace(self.problem, times=self.problem.times + dt),
                       trajectory=shifted(self.trajectory, dt))

    def without_knots(self) -> Route:
        """The route's waypoints without the planner's knots (the plan itself unchanged): what an
        edit is read against when the remainder is allocated again."""
        keep = self.labels != KNOT
        if np.all(keep):
            return self
        return replace(self, waypoints=self.waypoints[keep], times=self.times[keep], labels=self.labels[keep])


@dataclass(frozen=True)
class Outcome:
    """A planning attempt's result (ruckig style: expected failures are results, not raises)."""

    ok: bool
    route: Route | None = None
    message: str = ""
    blocked_waypoint: int | None = None  # mission index of a blocked waypoint
    stats: dict[str, Any] = field(default_factory=dict)
    blocked_segment: int | None = None  # route segment whose straight path crosses an obstacle
    obstacle: int | None = None  # index of that obstacle in the list given to the planner
    field: str | None = None  # the sender's field at fault (`durations[2]`, `start`), when one is
    mismatch: bool = False  # refused because the request does not fit how the vehicle is (start, initial)

    @property
    def status(self) -> OutcomeStatus:
        if self.ok:
            return OutcomeStatus.OK
        if self.mismatch:
            return OutcomeStatus.MISMATCH
        if self.blocked_waypoint is not None or self.blocked_segment is not None:
            return OutcomeStatus.BLOCKED
        return OutcomeStatus.INFEASIBLE


class OutcomeStatus(enum.Enum):
    OK = "ok"  # planned and verified
    BLOCKED = "blocked"  # an obstacle blocks a waypoint or a leg (and no detour was found)
    INFEASIBLE = "infeasible"  # no plan within the bounds (or not verified)
    MISMATCH = "mismatch"  # the mission does not fit where or how the vehicle is: no bound would help


def outside_map_text(mission: MissionSpec, waypoints: FloatArray, labels: FloatArray, wp: int | None) -> str | None:
    """A waypoint (or the current position) outside the map box, said as such with the box and
    the position: never "an obstacle" (issue 20.5)."""
    if wp is None or not 0 <= wp < len(waypoints):
        return None
    lo, hi, r = np.asarray(mission.map_lo), np.asarray(mission.map_hi), float(mission.radius)
    p = np.asarray(waypoints[wp], dtype=float)
    if np.all(p >= lo + r - 1e-9) and np.all(p <= hi - r + 1e-9):
        return None
    axis = int(np.argmax(np.maximum(lo + r - p, p - (hi - r))))
    high = p[axis] - (hi[axis] - r) > lo[axis] + r - p[axis]
    room = float(hi[axis] - p[axis] if high else p[axis] - lo[axis])  # to that face; < 0: beyond it
    floor = axis == 2 and high  # z is down
    if room < 0.0:
        where = f"{-room:.2f} m {'below the floor of' if floor else 'outside'}"
    else:  # inside, but the vehicle would not fit: say so, not "outside" (home 0.35 m above a landed PX4 SIH)
        where = f"only {room:.2f} m {'above the floor of' if floor else 'inside'}"
    f = mission.frame
    return (f"{waypoint_name(labels, wp)} {fmt_point(p, f)} is {where} the map box {fmt_box(lo, hi, f)} "
            f"(the geofence, relative to home once the autopilot reports it, intersected with the mission's map; "
            f"{f.upper()}, local frame) on axis {('xyz' if f != 'enu' else 'yxz')[axis]}: it must stay the vehicle "
            f"radius {r:g} m inside")


def plan_route(
    mission: MissionSpec,
    waypoints: FloatArray,
    times: FloatArray,
    labels: FloatArray,
    initial: FloatArray,
    obstacles: Known | Sequence[Polytope],
    cfg: Config,
    *,
    allocate: bool = False,
    neighbours: Any = None,
    candidates: int | None = None,
) -> Outcome:
    """Corridors, plan, verify. `initial` is the jet at waypoints[0] (time times[0]).

    `allocate`: the mission gave no durations, so only times[0] counts and the planner chooses
    the fastest durations the bounds and corridors allow (`planner_core.plan_mission`); it may
    insert knots on long legs, which join the route as synthetic waypoints (label KNOT), so no
    mission index ever counts one. `candidates`: the allocation's cap on candidate plans (in
    flight: what fits before the split; `planner_core.fastest_durations`'s max_candidates).
    """
    t0 = time.perf_counter()
    known = as_known(obstacles)
    try:
        corridors = build_corridors(waypoints, known.polytopes, mission)
    except CorridorError as exc:
        wp, seg, ob = exc.waypoint, exc.segment, exc.obstacle
        outside = outside_map_text(mission, waypoints, labels, wp) if ob is None else None
        what, blocked = (outside, None) if outside is not None else blocked_text(labels, seg, wp, known.name(ob))
        return Outcome(False, message=what, blocked_waypoint=blocked,
                       stats={"plan_seconds": time.perf_counter() - t0},
                       blocked_segment=seg if blocked is None else None, obstacle=ob)
    except Exception as exc:  # a geometry bug must be a refusal, not a crash
        return Outcome(False, message=f"corridor construction failed: {exc!r}",
                       stats={"plan_seconds": time.perf_counter() - t0})
    opts: dict[str, Any] = {"window": cfg.planner.window} if cfg.planner.method == "iterative" else {}
    if neighbours is not None:  # other vehicles' committed trajectories (companion.traffic)
        opts["neighbours"] = neighbours
    given = None if allocate else np.diff(times)
    # plan_mission verifies the plan once more itself: never fly on one check alone being trusted
    # the reserve is what a replan may spend: a pop-up's swerve from a fast start jet may need it
    reserves = (cfg.planner.reserve, 0.0) if allocate and cfg.planner.reserve > 0.0 else (0.0,)
    planned = 0  # candidate plans, for the service's estimate of its planning speed
    for reserve in reserves:
        mp = plan_mission(waypoints, mission.bounds, corridors, given, initial=initial, t0=float(times[0]),
                          method=cfg.planner.method, reserve=reserve, max_candidates=candidates, **opts)
        planned += int(mp.result.stats.get("allocation", {}).get("plans", 1))
        if mp.ok:
            break
    stats: dict[str, Any] = {"plan_seconds": time.perf_counter() - t0, "timing": mp.timing, "candidates": planned,
                             "capped": bool(mp.result.stats.get("allocation", {}).get("capped"))}
    if not mp.ok or mp.trajectory is None:
        diag = mp.result.diagnosis
        seg = diag.segment if diag is not None else None
        if seg is not None and 0 <= seg < len(mp.segment_source):
            seg = int(mp.segment_source[seg])  # knots the planner placed: the given leg they lie on
        if seg is not None and 0 <= seg < len(labels) - 1:
            field, text = failed_leg(mission, labels, seg, given is not None, mp.message)
            return Outcome(False, message=text, stats=stats, field=field)
        return Outcome(False, message=mp.message, stats=stats)
    p = mp.problem
    return Outcome(True, Route(mission, p.waypoints, p.times, mp.relabel(labels, KNOT), p, mp.trajectory),
                   mp.message, stats=stats)


_PLANNER_WHERE = re.compile(r"^infeasible at waypoint \d+(, segment \d+)?: ")
_OF_SEGMENT = re.compile(r" of segment \d+")


def failed_leg(mission: MissionSpec, labels: FloatArray, segment: int, timed: bool, message: str) -> tuple[str, str]:
    """The planner's failure on route segment `segment` in the sender's terms: the field (the
    duration the sender gave for that leg, else the waypoint it leads to) and the reason, with
    the leg named by its mission waypoints rather than the planner's segment numbers."""
    lab = np.asarray(labels, dtype=float)
    a, b = float(lab[segment]), float(lab[segment + 1])

    def name(x: float, start: bool) -> str:
        if x >= 0:
            return f"waypoint {int(x)}"
        return "where the vehicle is (the plan's start)" if start else "a point the companion placed (detour or knot)"

    leg = f"the leg from {name(a, segment == 0)} to {name(b, False)}"
    nxt = lab[segment + 1 :]
    ahead = nxt[nxt >= 0]
    first = mission.first_index
    field = f"waypoints[{int(ahead[0]) - first}]" if ahead.size else "waypoints"
    if timed and mission.durations is not None and b >= 1 and (a == b - 1 or (segment == 0 and a < 0 and b == first + 1)):
        k = int(b) - 1 - first
        if 0 <= k < len(mission.durations):
            field = f"durations[{k}]"
            leg += f" ({field} = {mission.durations[k]:.6g} s)"
    why = _OF_SEGMENT.sub("", _PLANNER_WHERE.sub("", message))
    why = why.replace(" fixed by the initial state", " (the leg's start is fixed by the vehicle's current velocity and "
                      "acceleration)")
    return field, f"{leg} cannot be planned: the {why}"


def clip_velocity(v: FloatArray, bounds: Bounds) -> FloatArray:
    out = np.asarray(np.clip(v, 0.98 * bounds.lo[0], 0.98 * bounds.hi[0]), dtype=float)
    # a horizontal norm bound is certified inside its polygon (radius r cos(pi / sides))
    cap = 0.98 * float(bounds.polygon_radius[0])
    h = float(np.hypot(out[0], out[1]))
    if h > cap:
        out[:2] *= cap / h
    return out
