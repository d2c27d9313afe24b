"""Mission -> verified route, and in-flight replanning of the remainder.

Pure functions over numpy and planner_core (no asyncio, no I/O): the service
calls them in a worker thread. Everything here is NED and in the flight's
time base (seconds since the companion took control).

A *route* is what is being flown: the remaining waypoints, their times, which
mission waypoint each one is (-1 for a synthetic one such as the split point),
the problem and its verified trajectory. A replan splits the flown trajectory
at `t_split` (a little ahead of now), keeps every waypoint after it, starts
from the exact jet of the old trajectory at `t_split` (so the setpoints stay
C^4 and the piece being flown does not change), rebuilds the corridors against
the current obstacles, plans, and verifies.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from companion.config import Config
from companion.messages import MessageError, check_geofence
from planner_core import changes as ch
from planner_core import plan, verify
from planner_core.bezier import end_jet, split_segment, start_jet
from planner_core.braking import braking_trajectory, stop_time_scale
from planner_core.changes import ChangeError, ChangeSet, parse_polytope
from planner_core.corridors import CorridorError, polytope_vertices
from planner_core.corridors import build_corridors as _build_corridors
from planner_core.problem import Bounds, FloatArray, Polytope, Problem, Trajectory, rest_jet
from planner_core.replan import Environment, ReplanOptions, replan
from planner_core.timing import allocate_times

INSIDE_EPS = 1e-9


# -- mission spec ---------------------------------------------------------------


@dataclass(frozen=True)
class MissionSpec:
    id: str
    waypoints: FloatArray  # (k, 3) NED goals
    durations: FloatArray | None  # (k-1,) or None: allocate
    bounds: Bounds
    obstacles: tuple[tuple[str, Polytope], ...]
    map_lo: FloatArray
    map_hi: FloatArray
    radius: float
    start: str  # "current" | "first_waypoint"
    autostart: bool
    initial: FloatArray | None  # (5, 3) for start == "first_waypoint"
    raw: dict[str, Any] = field(default_factory=dict, compare=False)


def _bound(value: Any, field_name: str) -> tuple[FloatArray, FloatArray]:
    if isinstance(value, int | float):
        hi = np.full(3, float(value))
        return -hi, hi
    arr = np.asarray(value, dtype=float)
    if arr.shape == (2,):
        lo, hi = np.full(3, arr[0]), np.full(3, arr[1])
    else:
        lo, hi = arr[:, 0], arr[:, 1]
    if np.any(lo >= 0) or np.any(hi <= 0):
        raise MessageError(field_name, "each interval must contain 0 (lo < 0 < hi)")
    return lo, hi


def bounds_from(obj: dict[str, Any] | None, cfg: Config) -> Bounds:
    b = cfg.planner.bounds
    base = Bounds.symmetric(b.velocity, b.acceleration, b.jerk, b.snap)
    lo, hi = base.lo.copy(), base.hi.copy()
    for row, name in enumerate(("velocity", "acceleration", "jerk", "snap")):
        if obj and name in obj:
            lo[row], hi[row] = _bound(obj[name], f"bounds.{name}")
    return Bounds(lo, hi)


def parse_region(obj: dict[str, Any], field_name: str) -> Polytope:
    try:
        poly = parse_polytope({k: v for k, v in obj.items() if k != "id"}, field_name)
    except ChangeError as exc:
        raise MessageError(exc.field, exc.reason) from None
    try:
        # Corridors need bounded, non-empty obstacles: refuse others here, not mid-replan.
        polytope_vertices(poly, field_name)
    except ValueError as exc:
        raise MessageError(field_name, str(exc).removeprefix(f"{field_name}: ")) from None
    return poly


def mission_from_message(obj: dict[str, Any], cfg: Config) -> MissionSpec:
    """A schema-valid mission dict, already in NED, to a MissionSpec (or MessageError)."""
    wps = np.asarray(obj["waypoints"], dtype=float)
    lo_g, hi_g = np.asarray(cfg.geofence.min), np.asarray(cfg.geofence.max)
    check_geofence(wps, lo_g, hi_g, "waypoints")
    start = obj.get("start", "current")
    if start == "first_waypoint" and len(wps) < 2:
        raise MessageError("waypoints", "start 'first_waypoint' needs at least 2 waypoints")
    durations = None
    if "durations" in obj:
        durations = np.asarray(obj["durations"], dtype=float)
    elif "times" in obj:
        durations = np.diff(np.asarray(obj["times"], dtype=float))
    map_lo, map_hi = lo_g, hi_g
    if "map" in obj:
        map_lo = np.maximum(lo_g, np.asarray(obj["map"]["min"], dtype=float))
        map_hi = np.minimum(hi_g, np.asarray(obj["map"]["max"], dtype=float))
        if np.any(map_lo >= map_hi):
            raise MessageError("map", "the map box does not overlap the geofence")
        check_geofence(wps, map_lo, map_hi, "waypoints")
    obstacles = tuple(
        (str(o.get("id", f"mission-{i}")), parse_region(o, f"obstacles[{i}]"))
        for i, o in enumerate(obj.get("obstacles", []))
    )
    initial = None
    if start == "first_waypoint":
        initial = rest_jet(wps[0])
        for row, name in enumerate(("velocity", "acceleration", "jerk", "snap"), start=1):
            if name in obj.get("initial", {}):
                initial[row] = obj["initial"][name]
    radius = max(cfg.planner.vehicle_radius, float(obj.get("vehicle_radius", 0.0)))
    return MissionSpec(
        id=str(obj["id"]),
        waypoints=wps,
        durations=durations,
        bounds=bounds_from(obj.get("bounds"), cfg),
        obstacles=obstacles,
        map_lo=map_lo,
        map_hi=map_hi,
        radius=radius,
        start=start,
        autostart=bool(obj.get("autostart", True)),
        initial=initial,
        raw=obj,
    )


# -- timing -----------------------------------------------------------------------


def allocate_durations(waypoints: FloatArray, bounds: Bounds, initial_velocity: FloatArray | None = None) -> FloatArray:
    """Segment durations for `waypoints` (planner_core.timing when present)."""
    times = allocate_times(waypoints, bounds, t0=0.0, initial_velocity=initial_velocity)
    return np.asarray(np.diff(times), dtype=float)


# -- geometry -----------------------------------------------------------------------


def inflate(poly: Polytope, radius: float) -> Polytope:
    return Polytope(poly.A, poly.b + radius * np.linalg.norm(poly.A, axis=1))


def first_hit(traj: Trajectory, t_from: float, obstacles: Sequence[Polytope], radius: float, dt: float = 0.01) -> float | None:
    """Earliest sampled time >= t_from at which the trajectory enters an inflated obstacle."""
    if t_from >= traj.t_end or not obstacles:
        return None
    ts = np.arange(t_from, traj.t_end + dt, dt)
    inflated = [inflate(ob, radius) for ob in obstacles]
    # Sample only segments whose control-point hull (which holds the curve) is not wholly
    # beyond one plane of some inflated obstacle: same answer, a fraction of the evaluations
    # (this runs on the event loop, before the replan).
    seg = np.clip(np.searchsorted(traj.times, ts, side="right") - 1, 0, traj.n_segments - 1)
    near = np.zeros(traj.n_segments, dtype=bool)
    for ob in inflated:
        beyond = np.min(traj.control_points @ ob.A.T - ob.b, axis=1) > -INSIDE_EPS  # (S, P)
        near |= ~np.any(beyond, axis=1)
    ts = ts[near[seg]]
    if ts.size == 0:
        return None
    pts = traj.evaluate(ts)
    inside = np.zeros(len(ts), dtype=bool)
    for ob in inflated:
        inside |= ob.contains(pts, tol=-INSIDE_EPS)
    if not np.any(inside):
        return None
    return float(ts[int(np.argmax(inside))])


def build_corridors(waypoints: FloatArray, obstacles: Sequence[Polytope], mission: MissionSpec) -> tuple[Polytope, ...]:
    return tuple(_build_corridors(waypoints, list(obstacles), (mission.map_lo, mission.map_hi), mission.radius))


# -- splicing -------------------------------------------------------------------------


def split_at(traj: Trajectory, t: float) -> tuple[Trajectory, int]:
    """The trajectory with a boundary at t (exact de Casteljau) and the index of that boundary."""
    times = traj.times
    if t <= times[0] + 1e-12:
        return traj, 0
    if t >= times[-1] - 1e-12:
        return traj, len(times) - 1
    j = int(np.searchsorted(times, t, side="right") - 1)
    if abs(times[j] - t) < 1e-12:
        return traj, j
    u = (t - times[j]) / (times[j + 1] - times[j])
    left, right = split_segment(traj.control_points[j], u)
    ctrl = np.concatenate([traj.control_points[:j], left[None], right[None], traj.control_points[j + 1 :]])
    new_times = np.concatenate([times[: j + 1], [t], times[j + 1 :]])
    cors = None
    if traj.corridors is not None:
        cors = (*traj.corridors[: j + 1], traj.corridors[j], *traj.corridors[j + 1 :])
    return Trajectory(new_times, ctrl, cors, dict(traj.stats)), j + 1


def splice(old: Trajectory, new: Trajectory) -> Trajectory:
    """Old up to new.t0, then new. The caller guarantees the jets agree at new.t0."""
    if new.t0 > old.t_end + 1e-9:
        # The old plan ended at rest: fill the wait with a hold at its end point.
        end = old.control_points[-1, -1]
        filler = np.repeat(end[None, None, :], 10, axis=1)
        filled = None if old.corridors is None else (*old.corridors, None)
        old = Trajectory(np.append(old.times, new.t0), np.concatenate([old.control_points, filler]), filled, old.stats)
        head, k = old, old.n_segments
    elif new.t0 >= old.t_end - 1e-12:
        head, k = old, old.n_segments
    else:
        head, k = split_at(old, new.t0)
    ctrl = np.concatenate([head.control_points[:k], new.control_points])
    times = np.concatenate([head.times[:k], new.times])
    cors: tuple[Polytope | None, ...] | None = None
    if head.corridors is not None or new.corridors is not None:
        hc = head.corridors or (None,) * head.n_segments
        nc = new.corridors or (None,) * new.n_segments
        cors = (*hc[:k], *nc)
    # Keep the spliced trajectory short: pieces long past are never sampled again.
    return Trajectory(times, ctrl, cors, dict(new.stats))


def trim_before(traj: Trajectory, t: float) -> Trajectory:
    """Drop whole segments that ended before t (never sampled again)."""
    k = int(np.searchsorted(traj.times, t, side="right")) - 2
    if k <= 0:
        return traj
    cors = None if traj.corridors is None else traj.corridors[k:]
    return Trajectory(traj.times[k:], traj.control_points[k:], cors, traj.stats)


# -- planning ---------------------------------------------------------------------------


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


@dataclass(frozen=True)
class Outcome:
    ok: bool
    route: Route | None = None
    message: str = ""
    blocked_waypoint: int | None = None  # mission index of a blocked waypoint
    stats: dict[str, Any] = field(default_factory=dict)
    blocked_segment: int | None = None  # route segment whose straight path crosses an obstacle
    obstacle: int | None = None  # index of that obstacle in the list given to the planner


def _plan_problem(problem: Problem, cfg: Config) -> tuple[Trajectory | None, str]:
    opts: dict[str, Any] = {}
    if cfg.planner.method == "iterative":
        opts["window"] = cfg.planner.window
    result = plan(problem, method=cfg.planner.method, **opts)
    if not result.ok or result.trajectory is None:
        return None, result.message
    traj = result.trajectory
    checked = problem if np.array_equal(traj.times, problem.times) else replace(problem, times=traj.times)
    report = verify(traj, checked)
    if not report.ok:  # plan() verifies too; never fly on one check alone being trusted
        return None, "verification failed: " + report.summary()
    return traj, result.message


def plan_route(
    mission: MissionSpec,
    waypoints: FloatArray,
    times: FloatArray,
    labels: FloatArray,
    initial: FloatArray,
    obstacles: Sequence[Polytope],
    cfg: Config,
) -> Outcome:
    """Corridors, plan, verify. `initial` is the jet at waypoints[0] (time times[0])."""
    t0 = time.perf_counter()
    try:
        corridors = build_corridors(waypoints, obstacles, mission)
    except CorridorError as exc:
        wp, seg = getattr(exc, "waypoint", None), getattr(exc, "segment", None)

        def name(i: int) -> str:
            if labels[i] >= 0:
                return f"mission waypoint {int(labels[i])}"
            return "the current position" if i == 0 else "a detour point"

        blocked = None
        if seg is not None and 0 <= seg < len(labels) - 1:
            what = f"the path from {name(seg)} to {name(seg + 1)} is blocked"
        elif wp is not None and 0 <= wp < len(labels):
            what = f"{name(wp)} is blocked"
            blocked = int(labels[wp]) if labels[wp] >= 0 else None
        else:
            what = "no free corridor"
        return Outcome(False, message=f"{what} (planner: {exc})", blocked_waypoint=blocked,
                       stats={"plan_seconds": time.perf_counter() - t0},
                       blocked_segment=seg if blocked is None else None, obstacle=getattr(exc, "obstacle", None))
    except Exception as exc:  # a geometry bug must be a refusal, not a crash
        return Outcome(False, message=f"corridor construction failed: {exc!r}",
                       stats={"plan_seconds": time.perf_counter() - t0})
    final = rest_jet(waypoints[-1])
    problem = Problem(waypoints, times, mission.bounds, initial, final, corridors)
    traj, message = _plan_problem(problem, cfg)
    stats = {"plan_seconds": time.perf_counter() - t0}
    if traj is None:
        return Outcome(False, message=message, stats=stats)
    problem = replace(problem, times=traj.times)
    return Outcome(True, Route(mission, waypoints, traj.times, labels, problem, traj), message, stats=stats)


def clip_velocity(v: FloatArray, bounds: Bounds) -> FloatArray:
    return np.asarray(np.clip(v, 0.98 * bounds.lo[0], 0.98 * bounds.hi[0]), dtype=float)


def start_mission(
    mission: MissionSpec,
    initial: FloatArray,
    t_start: float,
    obstacles: Sequence[Polytope],
    cfg: Config,
) -> Outcome:
    """Plan a fresh mission from the jet `initial` at `t_start`."""
    wps = mission.waypoints
    labels = np.arange(len(wps), dtype=float)
    jet = np.array(initial, dtype=float)
    if mission.start == "first_waypoint":
        gap = float(np.linalg.norm(jet[0] - wps[0]))
        if gap > cfg.safety.arrival_tolerance:
            return Outcome(False, message=f"start 'first_waypoint': vehicle is {gap:.2f} m from waypoint 0 "
                           f"(tolerance {cfg.safety.arrival_tolerance} m)")
        assert mission.initial is not None
        jet = mission.initial.copy()
        jet[0] = wps[0]
        points, lab = wps, labels
    else:
        jet[1] = clip_velocity(jet[1], mission.bounds)
        points = np.vstack([jet[0], wps])
        lab = np.concatenate([[-1.0], labels])
    # Already at waypoint 0 (a mission that starts where the vehicle is): the vehicle's position
    # stands for it. A lead segment of (nearly) zero length has a duration that its end jets
    # cannot fill without huge snap, and its plan fails verification at the start.
    at_first = mission.start != "first_waypoint" and len(wps) >= 2 and (
        float(np.linalg.norm(jet[0] - wps[0])) <= cfg.safety.arrival_tolerance)
    if at_first:
        points = np.vstack([jet[0], wps[1:]])
        lab = labels
    if mission.durations is not None and mission.start != "first_waypoint" and not at_first:
        lead = allocate_durations(points[:2], mission.bounds, jet[1])
        durations = np.concatenate([lead, mission.durations])
    elif mission.durations is not None:
        durations = mission.durations
    else:
        durations = allocate_durations(points, mission.bounds, jet[1])
    times = t_start + np.concatenate([[0.0], np.cumsum(durations)])
    all_obs = [*obstacles, *(p for _, p in mission.obstacles)]
    return plan_with_detours(mission, points, times, lab, jet, all_obs, cfg)


def replan_remainder(
    route: Route,
    active: Trajectory,
    t_split: float,
    obstacles: Sequence[Polytope],
    cfg: Config,
    waypoints: FloatArray | None = None,
    times: FloatArray | None = None,
    labels: FloatArray | None = None,
) -> Outcome:
    """Re-plan everything after t_split from the jet of `active` at t_split.

    `waypoints/times/labels` (defaults: the route's) may carry an edit; only
    the entries later than t_split are kept.
    """
    wps = route.waypoints if waypoints is None else waypoints
    tms = route.times if times is None else times
    lab = route.labels if labels is None else labels
    keep = tms > t_split + 1e-6
    if not np.any(keep):
        return Outcome(False, message="mission already complete: nothing left to replan")
    jet = active.jet(t_split)
    points = np.vstack([jet[0], wps[keep]])
    new_times = np.concatenate([[t_split], tms[keep]])
    new_labels = np.concatenate([[-1.0], lab[keep]])
    # A split just before a waypoint leaves a sliver of a segment: give it room.
    min_first = 0.3
    if new_times[1] - new_times[0] < min_first:
        new_times[1:] += min_first - (new_times[1] - new_times[0])
    all_obs = [*obstacles, *(p for _, p in route.mission.obstacles)]
    return plan_with_detours(route.mission, points, new_times, new_labels, jet, all_obs, cfg)


def plan_with_detours(
    mission: MissionSpec,
    points: FloatArray,
    times: FloatArray,
    labels: FloatArray,
    initial: FloatArray,
    obstacles: Sequence[Polytope],
    cfg: Config,
) -> Outcome:
    """plan_route, inserting detour points around obstacles that block straight legs."""
    outcome = plan_route(mission, points, times, labels, initial, obstacles, cfg)
    detours: list[Any] = []
    for _ in range(MAX_DETOURS):
        if outcome.ok or outcome.blocked_segment is None or outcome.obstacle is None:
            break
        detoured = detour(mission, points, times, labels, initial, obstacles, cfg,
                          outcome.blocked_segment, outcome.obstacle)
        if detoured is None:
            break
        outcome, points, times, labels = detoured
        detours += outcome.stats.get("detour", [])
    if outcome.ok and detours:
        outcome.stats["detour"] = detours
    return outcome


MAX_DETOURS = 3
DETOUR_MARGIN = 0.3


def detour_candidates(a: FloatArray, b: FloatArray, obstacle: Polytope, radius: float) -> list[FloatArray]:
    """Ways around an obstacle that sits across the straight path a -> b: left, right, over
    and under it. Each is one or two points (abreast of the obstacle's near and far faces),
    two radii plus a margin clear of it; shortest detour first."""
    verts = polytope_vertices(obstacle)
    length = float(np.linalg.norm(b - a))
    d = (b - a) / max(length, 1e-9)
    side = np.cross(d, [0.0, 0.0, 1.0])
    if np.linalg.norm(side) < 1e-6:  # a vertical path: any horizontal direction will do
        side = np.array([1.0, 0.0, 0.0])
    side /= np.linalg.norm(side)
    up = np.cross(side, d)
    clear = 2.0 * radius + DETOUR_MARGIN
    along = (verts - a) @ d
    near, far = float(along.min()) - clear, float(along.max()) + clear
    out = []
    for n in (side, -side, up, -up):
        lateral = float(np.max((verts - a) @ n)) + clear
        pts = [a + n * lateral + d * s for s in (near, far) if 0.0 < s < length]
        if not pts:
            pts = [a + n * lateral + d * float(np.clip(along.mean(), 0.0, length))]
        out.append(np.array(pts))
    return sorted(out, key=lambda p: float(np.sum(np.linalg.norm(np.diff(np.vstack([a, p, b]), axis=0), axis=1))))


def detour(
    mission: MissionSpec,
    points: FloatArray,
    times: FloatArray,
    labels: FloatArray,
    initial: FloatArray,
    obstacles: Sequence[Polytope],
    cfg: Config,
    segment: int,
    obstacle: int,
) -> tuple[Outcome, FloatArray, FloatArray, FloatArray] | None:
    """Insert a synthetic waypoint around the obstacle that blocks `segment` and re-plan."""
    if not 0 <= obstacle < len(obstacles):
        return None
    a, b = points[segment], points[segment + 1]
    best: tuple[Outcome, FloatArray, FloatArray, FloatArray] | None = None
    for cs in detour_candidates(a, b, obstacles[obstacle], mission.radius):
        if np.any(cs < mission.map_lo + mission.radius) or np.any(cs > mission.map_hi - mission.radius):
            continue
        k = len(cs)
        pts = np.insert(points, segment + 1, cs, axis=0)
        lab = np.insert(labels, segment + 1, np.full(k, -1.0))
        d = allocate_durations(pts[segment : segment + k + 2], mission.bounds,
                               initial[1] if segment == 0 else None)
        tms = np.insert(times, segment + 1, np.zeros(k))
        tms[segment + 1 : segment + k + 2] = times[segment] + np.cumsum(d)
        tms[segment + k + 2 :] = times[segment + 2 :] + (tms[segment + k + 1] - times[segment + 1])
        outcome = plan_route(mission, pts, tms, lab, initial, obstacles, cfg)
        if outcome.ok:
            outcome.stats["detour"] = [c.round(3).tolist() for c in cs]
            return outcome, pts, tms, lab
        if best is None and outcome.blocked_segment is not None and outcome.blocked_segment > segment + k:
            best = (outcome, pts, tms, lab)  # cleared this one; another obstacle further on
    return best


def brake(jet: FloatArray, bounds: Bounds, corridor: Polytope | None, t0: float) -> tuple[Trajectory | None, str]:
    """A verified stop to rest from `jet` at t0 inside `corridor` (None and why, if none)."""
    result = braking_trajectory(jet, bounds, corridor, t0)
    if not result.ok or result.trajectory is None:
        return None, result.message
    # braking_trajectory certifies its result with verify() before returning it.
    return result.trajectory, result.message


# A snap-limited stop takes about a second even from a slow speed (measured: the braking QP's
# durations grow 0.2 s * 1.5^k and slow stops land at k = 4), longer from speed.
MIN_STOP_SECONDS = 1.0
STOP_SAFETY_FACTOR = 1.5
BRAKE_MARGIN_SECONDS = 0.1


def stop_time_estimate(velocity: FloatArray, acceleration: FloatArray, bounds: Bounds) -> float:
    """A generous estimate (s) of a verified stop from any of the states (n, 3): the braking
    planner's time scale (`stop_time_scale`), scaled, never below MIN_STOP_SECONDS."""
    return float(max(MIN_STOP_SECONDS, STOP_SAFETY_FACTOR * stop_time_scale(velocity, acceleration, bounds)))


def brake_deadline(traj: Trajectory, t_now: float, t_hit: float, bounds: Bounds) -> float:
    """Latest trajectory time at which to start braking, given that `traj` enters an obstacle at
    t_hit: the time to hit minus a stop (estimated from the states between now and the hit) and
    a margin. It may lie in the past: brake at once then."""
    ts = np.linspace(t_now, max(t_now, min(t_hit, traj.t_end)), 9)
    stop = stop_time_estimate(traj.evaluate(ts, 1), traj.evaluate(ts, 2), bounds)
    return t_hit - stop - BRAKE_MARGIN_SECONDS


@dataclass(frozen=True)
class StopPlan:
    trajectory: Trajectory | None  # verified stop to rest, starting at `start` (None: none found)
    start: float
    message: str
    in_free_space: bool  # False: only the dynamic bounds were respected (last resort)


def plan_stop(
    base: Trajectory,
    starts: Sequence[float],
    clock: Callable[[], float],
    obstacles: Sequence[Polytope],
    mission: MissionSpec | None,
    bounds: Bounds,
    lead: float,
) -> StopPlan:
    """A verified stop branching off `base` at the latest of `starts` that works.

    `clock()` is the trajectory time now (this runs in a worker thread while `base` is being
    flown): a start is never earlier than clock() + lead, and a stop whose computation ran past
    its start (a busy computer) is planned again further ahead. Each start is tried inside a
    free corridor around the vehicle that excludes every obstacle (inflated by the vehicle
    radius), so the stop cannot enter one. If none works, the last resorts (`in_free_space`
    False, and the message says so) are a stop as soon as possible inside the corridor of the
    flown segment (planned before the newest obstacles), then within the dynamic bounds alone.
    """
    reasons: list[str] = []
    tried: set[float] = set()
    for want in sorted(starts, reverse=True):
        for _ in range(3):
            began = clock()
            t_b = max(float(want), began + lead)
            if round(t_b, 4) in tried:
                break
            tried.add(round(t_b, 4))
            jet = _jet_at(base, t_b)
            corridor = safe_corridor(jet[0], jet[1], obstacles, mission) if mission is not None else None
            if corridor is None:
                reasons.append(f"start t={t_b:.3f} s: no free corridor around the vehicle")
                break
            traj, why = brake(jet, bounds, corridor, t_b)
            if traj is None:
                reasons.append(f"start t={t_b:.3f} s: {why}")
                break
            if clock() <= t_b - 0.5 * lead:
                return StopPlan(traj, t_b, why, True)
            # Planned too slowly to be swapped in before its start: plan further ahead.
            lead = max(lead, 2.0 * (clock() - began))
    detail = "; ".join(reasons) or "no start given"
    t_b = clock() + lead
    jet = _jet_at(base, t_b)
    flown = corridor_at(base, t_b)
    if flown is not None:
        traj, why = brake(jet, bounds, flown, t_b)
        if traj is not None:
            return StopPlan(traj, t_b, f"no stop fits a free corridor ({detail}); stopping inside the flown "
                            "segment's corridor", False)
    traj, why = brake(jet, bounds, None, t_b)
    if traj is None:
        return StopPlan(None, t_b, f"{detail}; without a corridor: {why}", False)
    return StopPlan(traj, t_b, f"no stop fits a free corridor ({detail}); shortest stop within the "
                    "dynamic bounds only", False)


def _jet_at(traj: Trajectory, t: float) -> FloatArray:
    jet = traj.jet(min(t, traj.t_end))
    if t >= traj.t_end:
        jet[1:] = 0.0
    return jet


def corridor_at(traj: Trajectory, t: float) -> Polytope | None:
    if traj.corridors is None:
        return None
    j = int(np.clip(np.searchsorted(traj.times, t, side="right") - 1, 0, traj.n_segments - 1))
    return traj.corridors[j]


def safe_corridor(position: FloatArray, velocity: FloatArray, obstacles: Sequence[Polytope], mission: MissionSpec) -> Polytope | None:
    """A free polytope around `position` (for braking) that excludes every obstacle."""
    step = velocity / max(float(np.linalg.norm(velocity)), 1e-9) * 1e-3 if np.linalg.norm(velocity) > 1e-6 else np.array([1e-3, 0, 0])
    try:
        return build_corridors(np.vstack([position, position + step]), obstacles, mission)[0]
    except (CorridorError, ValueError):
        return None


def mission_index_to_route(route: Route, index: int) -> int | None:
    hits = np.nonzero(route.labels == index)[0]
    return int(hits[0]) if len(hits) else None


def finite(x: float) -> float | None:
    return x if math.isfinite(x) else None


def _route_index(route: Route, index: int, t_split: float, what: str) -> int:
    i = mission_index_to_route(route, index)
    if i is None:
        known = sorted(int(x) for x in route.labels if x >= 0)
        raise MessageError(f"{what}.index", f"mission waypoint {index} is not ahead of the vehicle (remaining: {known})")
    if route.times[i] <= t_split:
        raise MessageError(f"{what}.index", f"mission waypoint {index} has already been passed")
    return i


def _retime(points: FloatArray, times: FloatArray, i: int, bounds: Bounds) -> FloatArray:
    """Re-allocate the segments touching waypoint i and shift later times by the difference."""
    lo, hi = max(i - 1, 0), min(i + 1, len(points) - 1)
    d = allocate_durations(points[lo : hi + 1], bounds)
    new = times.copy()
    new[lo + 1 : hi + 1] = times[lo] + np.cumsum(d)
    new[hi + 1 :] = times[hi + 1 :] + (new[hi] - times[hi])
    return new


def apply_change(route: Route, change: dict[str, Any], t_split: float, cfg: Config) -> tuple[FloatArray, FloatArray, FloatArray, str]:
    """Edit the route's waypoints/times/labels per a `change` message (NED)."""
    wps, tms, lab = route.waypoints.copy(), route.times.copy(), route.labels.copy()
    lo, hi = route.mission.map_lo, route.mission.map_hi
    bounds = route.mission.bounds
    if "move_waypoint" in change:
        body = change["move_waypoint"]
        check_geofence([body["position"]], lo, hi, "move_waypoint.position")
        i = _route_index(route, body["index"], t_split, "move_waypoint")
        wps[i] = body["position"]
        return wps, tms, lab, f"moved waypoint {body['index']}"
    if "duration" in change:
        body = change["duration"]
        i = _route_index(route, body["index"] + 1, t_split, "duration")
        if i == 0 or lab[i - 1] not in (body["index"], -1):
            raise MessageError("duration.index", f"segment {body['index']} is not in the remaining mission")
        # If the segment is being flown its start is the last split point; the
        # new duration then counts from there.
        start = tms[i - 1]
        shift = start + body["value"] - tms[i]
        if start + body["value"] <= t_split + 0.05:
            raise MessageError("duration.value", "the new duration ends before the replanning point")
        tms[i:] += shift
        return wps, tms, lab, f"segment {body['index']} duration set to {body['value']} s"
    if "insert_waypoint" in change:
        body = change["insert_waypoint"]
        check_geofence([body["position"]], lo, hi, "insert_waypoint.position")
        j = body["index"]
        found = mission_index_to_route(route, j)
        if found is None:
            raise MessageError("insert_waypoint.index", f"mission waypoint {j} is not ahead of the vehicle; use append")
        i = found
        if tms[i] <= t_split:
            raise MessageError("insert_waypoint.index", f"mission waypoint {j} has already been passed")
        wps = np.insert(wps, i, body["position"], axis=0)
        tms = np.insert(tms, i, tms[i])
        lab = np.insert(lab, i, j)
        lab[i + 1 :] = np.where(lab[i + 1 :] >= 0, lab[i + 1 :] + 1, lab[i + 1 :])
        tms = _retime(wps, tms, i, bounds)
        return wps, tms, lab, f"inserted waypoint {j}"
    if "remove_waypoint" in change:
        body = change["remove_waypoint"]
        i = _route_index(route, body["index"], t_split, "remove_waypoint")
        if i == len(wps) - 1 and len(wps) <= 2:
            raise MessageError("remove_waypoint.index", "cannot remove the only remaining waypoint")
        wps, tms, lab = np.delete(wps, i, axis=0), np.delete(tms, i), np.delete(lab, i)
        lab[i:] = np.where(lab[i:] >= 0, lab[i:] - 1, lab[i:])
        tms = _retime(wps, tms, min(i, len(wps) - 1), bounds)
        return wps, tms, lab, f"removed waypoint {body['index']}"
    if "append" in change:
        body = change["append"]
        new = np.asarray(body["waypoints"], dtype=float)
        check_geofence(new, lo, hi, "append.waypoints")
        if "durations" in body:
            d = np.asarray(body["durations"], dtype=float)
        else:
            d = allocate_durations(np.vstack([wps[-1:], new]), bounds)
        start = max(tms[-1], t_split)
        nxt = int(np.max(lab)) + 1 if np.any(lab >= 0) else 0
        wps = np.vstack([wps, new])
        tms = np.concatenate([tms, start + np.cumsum(d)])
        lab = np.concatenate([lab, nxt + np.arange(len(new), dtype=float)])
        return wps, tms, lab, f"appended {len(new)} waypoints"
    raise MessageError("", "no change given")  # pragma: no cover - the schema requires one


# -- local replanning (paper section 3.1) via planner_core.replan ----------------------


def trim(route: Route, t: float) -> Route:
    """Drop waypoints (and segments) entirely before t; the rest is bit-for-bit the same."""
    k0 = int(np.searchsorted(route.times, t, side="right")) - 1
    if k0 <= 0:
        return route
    k0 = min(k0, len(route.times) - 2)
    tr = route.trajectory
    initial = start_jet(tr.control_points[k0], float(tr.times[k0 + 1] - tr.times[k0]))
    initial[0] = route.waypoints[k0]
    cors = None if route.problem.corridors is None else route.problem.corridors[k0:]
    problem = Problem(route.waypoints[k0:], route.times[k0:], route.problem.bounds, initial, route.problem.final, cors)
    traj = Trajectory(tr.times[k0:], tr.control_points[k0:], None if tr.corridors is None else tr.corridors[k0:], tr.stats)
    return Route(route.mission, route.waypoints[k0:], route.times[k0:], route.labels[k0:], problem, traj)


@dataclass(frozen=True)
class LocalEdit:
    """A planner_core edit in route indices plus how it renumbers the labels (picklable:
    it crosses to the planner process)."""

    edits: tuple[Any, ...]
    description: str
    # ("same",) | ("insert", route index, mission index) | ("remove", route index) | ("append", first, count)
    labels: tuple[Any, ...] = ("same",)

    def relabel(self, labels: FloatArray, wp: Any) -> FloatArray:
        """New labels; `wp` maps a route index before the split to one after it."""
        kind = self.labels[0]
        if kind == "insert":
            k = wp(self.labels[1])
            out = np.insert(labels, k, float(self.labels[2]))
            out[k + 1 :] = np.where(out[k + 1 :] >= 0, out[k + 1 :] + 1, out[k + 1 :])
            return out
        if kind == "remove":
            k = wp(self.labels[1])
            out = np.delete(labels, k)
            out[k:] = np.where(out[k:] >= 0, out[k:] - 1, out[k:])
            return out
        if kind == "append":
            return np.concatenate([labels, self.labels[1] + np.arange(self.labels[2], dtype=float)])
        return labels


def local_edit(route: Route, change: dict[str, Any], t_split: float) -> LocalEdit:
    """The `change` message as planner_core edits on the route (MessageError if impossible)."""
    lo, hi = route.mission.map_lo, route.mission.map_hi
    if "move_waypoint" in change:
        body = change["move_waypoint"]
        check_geofence([body["position"]], lo, hi, "move_waypoint.position")
        i = _route_index(route, body["index"], t_split, "move_waypoint")
        return LocalEdit((ch.MoveWaypoint(i, np.asarray(body["position"], dtype=float)),),
                         f"moved waypoint {body['index']}")
    if "duration" in change:
        body = change["duration"]
        i = _route_index(route, body["index"] + 1, t_split, "duration")
        if i == 0 or route.labels[i - 1] != body["index"]:
            raise MessageError("duration.index", f"segment {body['index']} is being flown or already passed")
        return LocalEdit((ch.SetDuration(i - 1, float(body["value"])),),
                         f"segment {body['index']} duration set to {body['value']} s")
    if "insert_waypoint" in change:
        body = change["insert_waypoint"]
        check_geofence([body["position"]], lo, hi, "insert_waypoint.position")
        j = body["index"]
        i = _route_index(route, j, t_split, "insert_waypoint")
        if i == 0:
            raise MessageError("insert_waypoint.index", f"cannot insert before mission waypoint {j}: it starts the route")

        return LocalEdit((ch.InsertWaypoint(i, np.asarray(body["position"], dtype=float)),),
                         f"inserted waypoint {j}", ("insert", i, j))
    if "remove_waypoint" in change:
        body = change["remove_waypoint"]
        i = _route_index(route, body["index"], t_split, "remove_waypoint")
        if i >= len(route.labels) - 1:
            raise MessageError("remove_waypoint.index", "cannot remove the final waypoint (send a new mission)")

        return LocalEdit((ch.RemoveWaypoint(i),), f"removed waypoint {body['index']}", ("remove", i))
    if "append" in change:
        body = change["append"]
        new = np.asarray(body["waypoints"], dtype=float)
        check_geofence(new, lo, hi, "append.waypoints")
        d = None if "durations" not in body else np.asarray(body["durations"], dtype=float)
        nxt = float(np.max(route.labels)) + 1 if np.any(route.labels >= 0) else 0.0

        return LocalEdit((ch.AppendWaypoints(new, d),), f"appended {len(new)} waypoints",
                         ("append", nxt, len(new)))
    raise MessageError("", "no change given")  # pragma: no cover - the schema requires one


def local_replan(
    route: Route,
    t_now: float,
    t_split: float,
    edit: LocalEdit,
    known_obstacles: Sequence[Polytope],
    cfg: Config,
) -> Outcome:
    """planner_core.replan with from_time = t_split: only the touched jets are re-solved."""
    t0 = time.perf_counter()
    r = trim(route, t_now)
    if t_split >= r.times[-1] - 1e-6 and not any(type(e).__name__ == "AppendWaypoints" for e in edit.edits):
        return Outcome(False, message="mission already complete: nothing left to replan")
    env = Environment(tuple(known_obstacles), (r.mission.map_lo, r.mission.map_hi), r.mission.radius)
    try:
        result = replan(r.problem, r.trajectory, ChangeSet(edit.edits, from_time=t_split),
                        options=ReplanOptions(environment=env))
    except ChangeError as exc:
        return Outcome(False, message=str(exc), stats={"plan_seconds": time.perf_counter() - t0})
    except Exception as exc:  # a planner bug must degrade to the next fallback, not crash the service
        return Outcome(False, message=f"local replan error: {exc!r}", stats={"plan_seconds": time.perf_counter() - t0})
    stats = {"plan_seconds": time.perf_counter() - t0, "method": "local", "resolved_jets": list(result.resolved_jets)}
    if not result.ok or result.trajectory is None:
        return Outcome(False, message=result.message, stats=stats)
    k = result.stats.get("split_index")
    labels = r.labels if k is None else np.insert(r.labels, int(k), -1.0)

    def wp(i: int) -> int:
        return i + 1 if k is not None and i >= int(k) else i

    labels = edit.relabel(labels, wp)
    p = result.problem
    traj = result.trajectory
    if len(labels) != p.m:
        return Outcome(False, message="internal: waypoint bookkeeping mismatch after replan", stats=stats)
    failure = verify_against(r, traj, p)
    stats["plan_seconds"] = time.perf_counter() - t0  # with the verification
    if failure is not None:
        return Outcome(False, message="verification failed: " + failure, stats=stats)
    return Outcome(True, Route(r.mission, p.waypoints, p.times, labels, p, traj), result.message, stats=stats)


def _same_polytope(a: Polytope | None, b: Polytope | None) -> bool:
    if a is b:
        return True
    if a is None or b is None:
        return False
    return a.A.shape == b.A.shape and bool(np.array_equal(a.A, b.A)) and bool(np.array_equal(a.b, b.b))


def verify_against(old: Route, traj: Trajectory, problem: Problem, tol: float = 1e-9) -> str | None:
    """Verify a local replan of `old` independently of the planner's own certificate, but
    only where it can differ (None if it passes, else why).

    A new segment whose control points and duration are bit-identical to a segment of the
    verified `old` route, under the same bounds, needs no new bound check: only a corridor
    check when its corridor changed (pop-ups add planes to many corridors). Every other
    segment is verified with planner_core.verify in a window that includes one neighbour on
    each side, so its junctions get verify's continuity check; windows at either end of the
    route check the problem's initial/final jets. Waypoints and times are checked everywhere.
    """
    m = problem.m
    ctrl = traj.control_points
    if ctrl.shape[0] != m - 1 or traj.times.shape != (m,) or not np.all(np.diff(traj.times) > 0):
        return "segments or times do not match the problem"
    if float(np.max(np.abs(traj.times - problem.times))) > 1e-9 * (1.0 + float(np.max(np.abs(problem.times)))):
        return "times differ from the problem's"
    ends = np.concatenate([ctrl[:, 0], ctrl[-1:, -1]])
    if float(np.max(np.abs(ends - problem.waypoints))) > tol:
        return "a segment does not start or end at its waypoint"
    same_bounds = bool(np.array_equal(old.problem.bounds.lo, problem.bounds.lo)
                       and np.array_equal(old.problem.bounds.hi, problem.bounds.hi))
    old_d = np.diff(old.trajectory.times)
    old_cors = old.problem.corridors or (None,) * old.trajectory.n_segments
    known: dict[bytes, list[Polytope | None]] = {}
    if same_bounds:
        for s in range(old.trajectory.n_segments):
            key = old.trajectory.control_points[s].tobytes() + old_d[s].tobytes()
            known.setdefault(key, []).append(old_cors[s])
    d = np.diff(traj.times)
    cors = problem.corridors or (None,) * (m - 1)
    full = np.ones(m - 1, dtype=bool)
    for s in range(m - 1):
        seen = known.get(ctrl[s].tobytes() + d[s].tobytes())
        if seen is None:
            continue
        full[s] = False
        c = cors[s]
        if c is not None and not any(_same_polytope(c, o) for o in seen) and c.A.shape[0]:
            v = float(np.max(ctrl[s] @ c.A.T - c.b))
            if v > tol:
                return f"segment {s} leaves its corridor by {v:.3g}"
    idx = np.flatnonzero(full)
    if idx.size == 0:
        return None
    # windows: runs of segments to verify, grown by one neighbour each side, merged
    lo_hi: list[list[int]] = []
    for s in idx.tolist():
        lo, hi = max(int(s) - 1, 0), min(int(s) + 1, m - 2)
        if lo_hi and lo <= lo_hi[-1][1] + 1:
            lo_hi[-1][1] = max(lo_hi[-1][1], hi)
        else:
            lo_hi.append([lo, hi])
    for lo, hi in lo_hi:
        initial = problem.initial if lo == 0 else start_jet(ctrl[lo], float(d[lo]))
        final = problem.final if hi == m - 2 else end_jet(ctrl[hi], float(d[hi]))
        sub_cors = None if problem.corridors is None else tuple(problem.corridors[lo : hi + 1])
        sub = Problem(problem.waypoints[lo : hi + 2], problem.times[lo : hi + 2], problem.bounds, initial, final, sub_cors)
        piece = Trajectory(traj.times[lo : hi + 2], ctrl[lo : hi + 1], sub_cors, traj.stats)
        report = verify(piece, sub, tol=tol)
        if not report.ok:
            return f"segments {lo}..{hi}: {report.summary()}"
    return None


def warm_up_replan(cfg: Config) -> bool:
    """A mission and a pop-up local replan on it: first-call costs of the replan path paid early."""
    spec = mission_from_message({"id": "warm-up", "waypoints": [[3.0, 0.0, -1.5], [3.0, 3.0, -1.5]]}, cfg)
    outcome = start_mission(spec, rest_jet(np.array([0.0, 0.0, -1.5])), 0.0, [], cfg)
    if not outcome.ok or outcome.route is None:
        return False
    eye = np.eye(3)
    box = Polytope(np.vstack([eye, -eye]), np.array([10.0, 10.0, 10.0, -9.0, -9.0, -9.0]))
    edit = LocalEdit((ch.AddObstacles((box,)),), "warm-up")
    return local_replan(outcome.route, 0.0, 0.5, edit, [], cfg).ok


def warm_up(cfg: Config) -> bool:
    """Plan and encode a tiny mission: imports and first-call caches are paid before flying."""
    spec = mission_from_message({"id": "warm-up", "waypoints": [[1.0, 0.0, -1.0], [1.0, 1.0, -1.0]]}, cfg)
    outcome = start_mission(spec, rest_jet(np.array([0.0, 0.0, -1.0])), 0.0, [], cfg)
    return outcome.ok


def check_mission(
    mission: MissionSpec,
    initial: FloatArray,
    t_start: float,
    obstacles: Sequence[Polytope],
    cfg: Config,
) -> Outcome:
    """start_mission's verdict without the route (which is large to send between processes)."""
    return replace(start_mission(mission, initial, t_start, obstacles, cfg), route=None)


def warm_up_brake(cfg: Config) -> bool:
    """A stop from speed next to an obstacle: first-call costs of the braking path paid early."""
    spec = mission_from_message({"id": "warm-up", "waypoints": [[3.0, 0.0, -1.5]]}, cfg)
    outcome = start_mission(spec, rest_jet(np.array([0.0, 0.0, -1.5])), 0.0, [], cfg)
    if not outcome.ok or outcome.route is None:
        return False
    traj = outcome.route.trajectory
    eye = np.eye(3)
    box = Polytope(np.vstack([eye, -eye]), np.array([2.6, 0.5, -1.0, -2.4, 0.5, 2.0]))
    mid = 0.5 * (traj.t0 + traj.t_end)
    return plan_stop(traj, [mid], lambda: traj.t0, [box], spec, spec.bounds, 0.05).trajectory is not None
