"""Plan a mission, replan its remainder, replan locally: pure orchestration over planner_core.

No asyncio, no I/O: the service calls these in worker threads or processes. Everything is
NED and in the flight's time base (seconds since the companion took control). A replan
splits the flown trajectory at `t_split` (a little ahead of now), keeps every waypoint after
it, starts from the exact jet of the old trajectory there (so the setpoints stay C^4 and the
piece being flown does not change), rebuilds the corridors against the known obstacles,
plans and verifies.
"""

from __future__ import annotations

import functools
import time
import traceback
from collections.abc import Callable, Sequence
from dataclasses import replace
from typing import Any, TypeVar

import numpy as np

from companion.config import Config
from companion.detours import plan_with_detours
from companion.edits import LocalEdit
from companion.obstacles import Known, as_known, blocked_text
from companion.route import KNOT, Outcome, Route, allocate_durations, clip_velocity
from companion.wire.messages import MissionSpec, mission_from_message
from planner_core import (
    AddObstacles,
    ChangeError,
    ChangeSet,
    Environment,
    FloatArray,
    Neighbours,
    Polytope,
    Problem,
    ReplanOptions,
    Trajectory,
    replan,
    rest_jet,
    start_jet,
    verify_changed,
)

F = TypeVar("F", bound=Callable[..., Outcome])


def answered(fn: F) -> F:
    """Every planning entry point answers with an Outcome: an exception from planner_core (a
    bug, or an input no check foresaw) becomes a refusal that says so, with the traceback in
    stats["internal_error"] for the service to log (these run in workers: the service logs)."""

    @functools.wraps(fn)
    def wrapper(*args: Any, **kwargs: Any) -> Outcome:
        try:
            return fn(*args, **kwargs)
        except Exception as exc:
            return Outcome(False, message=f"the planner failed on this input ({type(exc).__name__}: {str(exc)[:120]}); "
                           "this is a bug, logged by the companion", stats={"internal_error": traceback.format_exc()})

    return wrapper  # type: ignore[return-value]


# m/s, m/s^2: how far the flown velocity and acceleration at waypoint 0 may be from a
# 'first_waypoint' mission's `initial` (its default: at rest; a hover's wobble stays well inside)
INITIAL_TOLERANCE = (0.3, 1.0)


@answered
def start_mission(mission: MissionSpec, initial: FloatArray, t_start: float, known: Known | Sequence[Polytope],
                  cfg: Config, neighbours: Neighbours | None = None, candidates: int | None = None,
                  quick: bool = False) -> Outcome:
    """Plan a fresh mission from the jet `initial` at `t_start`; `candidates`: plan_route's cap.
    `quick`: a mission without durations is planned on the default allocation alone (one plan,
    stretched where it is infeasible, as a timed mission is) instead of the search for the
    fastest durations: the companion's anytime start flies it at once and swaps the search's
    plan in later (MissionStart.improve); the route keeps the mission as sent (no durations), so
    what is planned from it later chooses its durations again."""
    wps = mission.waypoints
    labels = mission.first_index + np.arange(len(wps), dtype=float)
    jet = np.array(initial, dtype=float)
    if mission.start == "first_waypoint":
        gap = float(np.linalg.norm(jet[0] - wps[0]))
        if gap > cfg.safety.arrival_tolerance:
            return Outcome(False, message=f"start 'first_waypoint': vehicle is {gap:.2f} m from waypoint 0 "
                           f"(tolerance {cfg.safety.arrival_tolerance} m: [safety] arrival_tolerance); fly there "
                           "first, or send start 'current'", field="start", mismatch=True)
        # The flown state stands for waypoint 0, as for a mission that starts where the vehicle
        # is: a plan from waypoint 0 itself (a few cm off: home moves ~1 cm when ArduCopter arms,
        # and waypoints given from home move with it) or from another `initial` jet could not be
        # spliced onto what is flown. `initial` says what the vehicle's motion there must be.
        assert mission.initial is not None
        dv = float(np.linalg.norm(mission.initial[1] - jet[1]))
        da = float(np.linalg.norm(mission.initial[2] - jet[2]))
        if dv > INITIAL_TOLERANCE[0] or da > INITIAL_TOLERANCE[1]:
            return Outcome(False, message=f"start 'first_waypoint': the vehicle's velocity {np.round(jet[1], 2).tolist()} "
                           f"m/s and acceleration {np.round(jet[2], 2).tolist()} m/s^2 at waypoint 0 are not the "
                           f"mission's initial ones ({np.round(mission.initial[1], 2).tolist()}, "
                           f"{np.round(mission.initial[2], 2).tolist()}; default: at rest): send start 'current', or "
                           "an initial that matches", field="initial", mismatch=True)
    jet[1] = clip_velocity(jet[1], mission.bounds)
    points = np.vstack([jet[0], wps])
    lab = np.concatenate([[-1.0], labels])
    # Already at waypoint 0 (a mission that starts where the vehicle is): the vehicle's position
    # stands for it. A lead segment of (nearly) zero length has a duration that its end jets
    # cannot fill without huge snap, and its plan fails verification at the start.
    at_first = len(wps) >= 2 and (
        mission.start == "first_waypoint" or float(np.linalg.norm(jet[0] - wps[0])) <= cfg.safety.arrival_tolerance)
    if at_first:
        points = np.vstack([jet[0], wps[1:]])
        lab = labels
    if mission.durations is not None and not at_first:
        lead = allocate_durations(points[:2], mission.bounds, jet[1])
        durations = np.concatenate([lead, mission.durations])
    elif mission.durations is not None:
        durations = mission.durations
    else:
        durations = allocate_durations(points, mission.bounds, jet[1])
    times = t_start + np.concatenate([[0.0], np.cumsum(durations)])
    # No durations given and [planner] timing = "fastest": the fastest the bounds allow (the
    # allocation above then only gives t0 and the detour points' first guess).
    fastest = mission.durations is None and cfg.planner.timing == "fastest" and not quick
    out = plan_with_detours(mission, points, times, lab, jet, as_known(known) + Known.of(mission.obstacles), cfg,
                            allocate=fastest, neighbours=neighbours, candidates=candidates)
    if quick and mission.durations is None:
        out.stats["quick"] = True
    return out


# s: how long a vehicle at rest may wait for the others before it starts a mission no separated
# plan can fly at once (two crossing vehicles timed to meet: the later one starts a little later)
FLEET_DELAYS = (0.5, 1.0, 2.0, 3.0, 4.0, 6.0, 8.0)
FLEET_DELAY_BUDGET = 2.0  # s of planning spent on later starts at most (an untimed mission plans slowly)


@answered
def start_separated(mission: MissionSpec, initial: FloatArray, t_start: float, known: Known | Sequence[Polytope],
                    cfg: Config, neighbours: Neighbours | None = None, candidates: int | None = None) -> Outcome:
    """start_mission against the other vehicles' trajectories; when no plan keeps the separation
    and the vehicle is at rest, the same mission started later (FLEET_DELAYS: it holds where it
    is meanwhile; stats `fleet_delay`). A timed mission keeps its durations."""
    if neighbours is not None and neighbours.trajectories and len(mission.waypoints):
        # both hold their last points for ever: a last waypoint too near another vehicle's final
        # hold can never be separated, however the mission is planned or delayed
        nb = neighbours.for_bounds(mission.bounds)
        last = np.asarray(mission.waypoints[-1], dtype=float)
        for k, tr in enumerate(nb.trajectories):
            gap = float(np.linalg.norm(last - tr.control_points[-1, -1]))
            if gap < nb.required(k):
                return Outcome(False, message=f"separation: the mission's last waypoint is {gap:.2f} m from the "
                               f"final hold of neighbour {k}, which stays reserved ({nb.required(k):.2f} m required)",
                               field=f"waypoints[{len(mission.waypoints) - 1}]")
    t0 = time.perf_counter()
    out = start_mission(mission, initial, t_start, known, cfg, neighbours, candidates)
    if out.ok or neighbours is None or not neighbours.trajectories or "separation" not in out.message:
        return out
    if float(np.max(np.abs(np.asarray(initial, dtype=float)[1:]))) > 1e-3:
        return out
    for delay in FLEET_DELAYS:
        if time.perf_counter() - t0 > FLEET_DELAY_BUDGET:
            return replace(out, message=out.message + f" (and starting up to {delay:g} s later; gave up after "
                           f"{FLEET_DELAY_BUDGET:g} s of planning)")
        later = start_mission(mission, initial, t_start + delay, known, cfg, neighbours, candidates)
        if later.ok:
            later.stats["fleet_delay"] = delay
            return later
    return replace(out, message=out.message + f" (and starting up to {FLEET_DELAYS[-1]:g} s later)")


@answered
def check_mission(mission: MissionSpec, initial: FloatArray, t_start: float, known: Known | Sequence[Polytope],
                  cfg: Config) -> Outcome:
    """start_mission's verdict without the route (which is large to send between processes)."""
    return replace(start_mission(mission, initial, t_start, known, cfg), route=None)


@answered
def replan_remainder(route: Route, active: Trajectory, t_split: float, known: Known | Sequence[Polytope], cfg: Config,
                     waypoints: FloatArray | None = None, times: FloatArray | None = None,
                     labels: FloatArray | None = None, *, allocate: bool = False,
                     neighbours: Neighbours | None = None, candidates: int | None = None) -> Outcome:
    """Re-plan everything after t_split from the jet of `active` at t_split.

    `waypoints/times/labels` (defaults: the route's) may carry an edit; only the entries
    later than t_split are kept. `allocate`: the mission gave no durations, so the planner
    chooses them again from the split (`plan_route`), and places its own knots: the old ones
    are dropped (one may now lie in an obstacle). `candidates`: plan_route's cap on the
    fastest-allocation search (in flight: what fits before the split).
    """
    wps = route.waypoints if waypoints is None else waypoints
    tms = route.times if times is None else times
    lab = route.labels if labels is None else labels
    keep = tms > t_split + 1e-6
    if allocate:
        keep &= lab != KNOT
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
    return plan_with_detours(route.mission, points, new_times, new_labels, jet,
                             as_known(known) + Known.of(route.mission.obstacles), cfg, allocate=allocate,
                             neighbours=neighbours, candidates=candidates)


def remaining(route: Route, t: float) -> MissionSpec | None:
    """The mission waypoints not yet reached at t, as a mission flown from where the vehicle is."""
    keep = (route.times > t) & (route.labels >= 0)
    if not np.any(keep):
        return None
    # Mission indices stay those published: waypoint i of the mission keeps its index i.
    first = int(route.labels[keep][0])
    return replace(route.mission, waypoints=route.waypoints[keep], durations=None, start="current", initial=None,
                   first_index=first)


# -- local replanning (paper section 3.1) via planner_core.replan -----------------------


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


def local_replan(route: Route, t_split: float, edit: LocalEdit, known: Known | Sequence[Polytope],
                 cfg: Config, neighbours: Neighbours | None = None) -> Outcome:
    """planner_core.replan with from_time = t_split: only the touched jets are re-solved.

    `route` is the trimmed route the edit was resolved against (edits.resolve), so the
    edit's indices are this route's."""
    t0 = time.perf_counter()
    r = route
    if t_split >= r.times[-1] - 1e-6 and not any(type(e).__name__ == "AppendWaypoints" for e in edit.edits):
        return Outcome(False, message="mission already complete: nothing left to replan")
    every = as_known(known) + Known.of(r.mission.obstacles)
    new = [p for e in edit.edits if isinstance(e, AddObstacles) for p in e.obstacles]
    before = every.without(new)
    named_new = every.only(new)
    env = Environment(before.polytopes, r.mission.corridor_map, r.mission.radius)
    try:
        result = replan(r.problem, r.trajectory, ChangeSet(edit.edits, from_time=t_split),
                        options=ReplanOptions(environment=env, neighbours=neighbours))
    except ChangeError as exc:
        return Outcome(False, message=str(exc), stats={"plan_seconds": time.perf_counter() - t0})
    except Exception as exc:  # a planner bug must degrade to the next fallback, not crash the service
        return Outcome(False, message=f"local replan error: {exc!r}", stats={"plan_seconds": time.perf_counter() - t0,
                                                                              "internal_error": traceback.format_exc()})
    stats = {"plan_seconds": time.perf_counter() - t0, "method": "local", "resolved_jets": list(result.resolved_jets)}
    if not result.ok or result.trajectory is None:
        split = result.stats.get("split_index")
        labels = r.labels if split is None else np.insert(r.labels, int(split), -1.0)
        return Outcome(False, message=_replan_failure(result.message, result.diagnosis, labels, before + named_new),
                       stats=stats)
    k = result.stats.get("split_index")
    labels = r.labels if k is None else np.insert(r.labels, int(k), -1.0)

    def wp(i: int) -> int:
        return i + 1 if k is not None and i >= int(k) else i

    labels = edit.relabel(labels, wp)
    p = result.problem
    traj = result.trajectory
    if len(labels) != p.m:
        return Outcome(False, message="internal: waypoint bookkeeping mismatch after replan", stats=stats)
    failure = verify_changed(r.trajectory, r.problem, traj, p)
    stats["plan_seconds"] = time.perf_counter() - t0  # with the verification
    if failure is not None:
        return Outcome(False, message="verification failed: " + failure, stats=stats)
    return Outcome(True, Route(r.mission, p.waypoints, p.times, labels, p, traj), result.message, stats=stats)


def _replan_failure(message: str, diagnosis: dict[str, object] | None, labels: FloatArray, names: Known) -> str:
    """planner_core.replan's failure in mission terms: its indices are those of the route
    with the split point inserted (`labels`); its obstacles those known before, then the new."""
    if not diagnosis or diagnosis.get("kind") != "corridor":
        return message
    ob, seg, wpt = diagnosis.get("obstacle"), diagnosis.get("segment"), diagnosis.get("waypoint")
    name = names.name(ob if isinstance(ob, int) else None)
    text, _ = blocked_text(labels, seg if isinstance(seg, int) else None, wpt if isinstance(wpt, int) else None, name)
    return text


# -- first-call costs paid before flying -------------------------------------------------


def warm_up(cfg: Config) -> bool:
    """Plan a tiny mission: imports and first-call caches are paid before flying."""
    spec = mission_from_message({"id": "warm-up", "waypoints": [[1.0, 0.0, -1.0], [1.0, 1.0, -1.0]]}, cfg)
    return start_mission(spec, rest_jet(np.array([0.0, 0.0, -1.0])), 0.0, Known(), cfg).ok


def warm_up_replan(cfg: Config) -> bool:
    """A mission and a pop-up local replan on it: first-call costs of the replan path paid early."""
    spec = mission_from_message({"id": "warm-up", "waypoints": [[3.0, 0.0, -1.5], [3.0, 3.0, -1.5]]}, cfg)
    outcome = start_mission(spec, rest_jet(np.array([0.0, 0.0, -1.5])), 0.0, Known(), cfg)
    if not outcome.ok or outcome.route is None:
        return False
    eye = np.eye(3)
    box = Polytope(np.vstack([eye, -eye]), np.array([10.0, 10.0, 10.0, -9.0, -9.0, -9.0]))
    edit = LocalEdit((AddObstacles((box,)),), "warm-up")
    return local_replan(trim(outcome.route, 0.0), 0.5, edit, Known(("warm-up",), (box,)), cfg).ok
