"""A mission planned in one call: waypoints, bounds, corridors, optional durations and a timing mode
in; the verified trajectory and the way back to the caller's waypoint indices out.

`plan_mission` is what a client (the companion, the CLI) calls instead of choosing between
`plan`, `fastest_durations` and `weighted_durations` itself. Timing modes (`TIMINGS`):

- "auto" (the default): the given durations when there are any (the planner's recovery
  stretches them if they are infeasible), else the fastest the bounds and corridors allow
  (`allocation.fastest_durations`);
- "fastest": the fastest allocation even when durations are given (they are ignored);
- "default": the given durations, else `timing.allocate_times` (the slower allocation that
  was the default before the fastest one).
`time_weight` (rho > 0) chooses the durations minimising J + rho T instead, whatever the mode.
`reserve` (0 <= r < 1) keeps a share of every bound unused by an allocated plan: the durations
are chosen, and the trajectory planned and verified, within (1 - r) x the bounds, while the
planned problem keeps the full bounds. A later replan (a pop-up obstacle, a moved waypoint) is
checked against the full bounds, so it has the reserve to swerve or brake with. Given
durations ignore it.

The fastest allocation may split long legs with knots (extra waypoints on the straight leg,
inside its corridor). The planned problem then has more waypoints than the caller gave:
`waypoint_index[i]` is where the caller's waypoint i sits in it, `segment_source[s]` the
caller's segment that planned segment s lies on, and `relabel` maps per-waypoint labels
(mission indices) onto the planned waypoints with a fill value for the knots, so that no
message ever counts a knot as a waypoint.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, replace
from math import factorial
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner_core.errors import FieldError
from planner_core.planning import plan
from planner_core.problem import Bounds, FloatArray, Polytope, Problem, Trajectory
from planner_core.result import PlanResult, PlanStatus
from planner_core.verify import verify

IntArray = NDArray[np.int64]
TIMINGS = ("auto", "fastest", "default")

__all__ = ["TIMINGS", "MissionPlan", "plan_mission"]


@dataclass(frozen=True)
class MissionPlan:
    result: PlanResult  # the verified plan, or the failure (status, message, diagnosis)
    problem: Problem  # what was planned: the given waypoints plus any knots, at the planned times
    waypoint_index: IntArray  # (n,) per given waypoint, its index in `problem`
    timing: str  # what chose the durations: "given", "default", "fastest" or "time-weight"

    @property
    def ok(self) -> bool:
        return self.result.ok

    @property
    def status(self) -> PlanStatus:
        return self.result.status

    @property
    def message(self) -> str:
        return self.result.message

    @property
    def trajectory(self) -> Trajectory | None:
        return self.result.trajectory

    @property
    def durations(self) -> FloatArray:
        return self.problem.durations

    @property
    def segment_source(self) -> IntArray:
        """(planned segments,) the given segment each planned segment lies on."""
        owner = np.zeros(self.problem.m - 1, dtype=np.int64)
        owner[self.waypoint_index[1:-1]] = 1
        return np.cumsum(owner)

    def relabel(self, labels: ArrayLike, fill: float = -1.0) -> FloatArray:
        """Per-waypoint `labels` of the given waypoints, onto the planned ones; knots get `fill`."""
        lab = np.asarray(labels, dtype=float)
        if lab.shape != self.waypoint_index.shape:
            raise FieldError("labels", f"expected {self.waypoint_index.size} entries (one per given waypoint), "
                                       f"got shape {lab.shape}")
        out = np.full(self.problem.m, fill, dtype=float)
        out[self.waypoint_index] = lab
        return out


def plan_mission(
    waypoints: ArrayLike,
    bounds: Bounds,
    corridors: Sequence[Polytope | None] | None = None,
    durations: ArrayLike | None = None,
    *,
    timing: str = "auto",
    time_weight: float | None = None,
    reserve: float = 0.0,
    initial: ArrayLike | None = None,
    final: ArrayLike | None = None,
    t0: float = 0.0,
    method: str = "iterative",
    max_candidates: int | None = None,
    **opts: Any,
) -> MissionPlan:
    """Plan and verify a mission (module docstring). `initial` / `final`: (5, 3) jets at the
    first / last waypoint (rest when None); `t0`: the time of the first waypoint; `opts` go to
    `plan` (window, cost, backend, ...); `max_candidates` caps the fastest allocation's search
    (`fastest_durations`; the other timings plan once). Bad input raises `FieldError` naming the argument;
    an infeasible mission is a result (`ok` False, `message`, `result.diagnosis`)."""
    if timing not in TIMINGS:
        raise FieldError("timing", f"expected one of {', '.join(TIMINGS)}, got {timing!r}")
    if time_weight is not None and not (np.isfinite(time_weight) and time_weight > 0.0):
        raise FieldError("time_weight", f"must be finite and > 0, got {time_weight}")
    if not (np.isfinite(reserve) and 0.0 <= reserve < 1.0):
        raise FieldError("reserve", f"must be in [0, 1), got {reserve}")
    if not np.isfinite(t0):
        raise FieldError("t0", f"must be finite, got {t0}")
    wps = np.asarray(waypoints, dtype=float)
    if wps.ndim != 2 or wps.shape[1] != 3 or wps.shape[0] < 2:
        raise FieldError("waypoints", f"expected (m >= 2, 3) positions, got shape {wps.shape}")
    if not np.all(np.isfinite(wps)):
        raise FieldError(f"waypoints[{int(np.argwhere(~np.isfinite(wps))[0, 0])}]", "must be finite")
    m = wps.shape[0]
    cors: tuple[Polytope | None, ...] | None = None
    if corridors is not None:
        cors = tuple(corridors)
        if len(cors) != m - 1:
            raise FieldError("corridors", f"has {len(cors)} entries for {m - 1} segments")
    init = _jet(initial, wps[0], "initial")
    fin = _jet(final, wps[-1], "final")
    given: FloatArray | None = None
    if durations is not None:
        given = np.asarray(durations, dtype=float).reshape(-1)
        if given.shape != (m - 1,):
            raise FieldError("durations", f"has {given.size} entries for {m - 1} segments")
        bad = np.flatnonzero(~(np.isfinite(given) & (given > 0.0)))
        if bad.size:
            raise FieldError(f"durations[{int(bad[0])}]", f"must be finite and > 0, got {given[bad[0]]:g}")
    within = bounds.scaled(1.0 - reserve) if reserve > 0.0 else bounds
    if time_weight is None and (timing == "default" or (given is not None and timing != "fastest")):
        mp = _fixed(wps, bounds, within, cors, given, init, fin, t0, method, opts)
        if mp.ok or not np.any(init[1:]):
            return mp
        led = _fixed_with_lead(wps, bounds, within, cors, given, init, fin, t0, method, opts)
        return led if led is not None and led.ok else mp
    from planner_core.allocation import fastest_durations, weighted_durations

    seed = Problem.from_waypoints(wps, np.ones(m - 1), within, cors, init, fin, t0)  # only t0 of its times counts
    if time_weight is not None:
        alloc = weighted_durations(seed, time_weight, method, **opts)
        mode = "time-weight"
    else:
        alloc = fastest_durations(seed, method, max_candidates=max_candidates, **opts)
        mode = "fastest"
    return _full(_checked(MissionPlan(alloc.result, alloc.problem, alloc.waypoint_index, mode)), bounds)


def _fixed(wps: FloatArray, bounds: Bounds, within: Bounds, cors: tuple[Polytope | None, ...] | None,
           given: FloatArray | None, init: FloatArray, fin: FloatArray, t0: float, method: str,
           opts: dict[str, Any]) -> MissionPlan:
    """A plan on durations fixed before planning: the given ones (the planner's recovery may
    stretch them), else the default allocation within the reserve."""
    same = np.arange(wps.shape[0], dtype=np.int64)
    if given is not None:
        return _planned(Problem.from_waypoints(wps, given, bounds, cors, init, fin, t0), same, "given", method, opts)
    from planner_core.timing import allocate_times

    # as the loader and the companion always did: from the legs and the start velocity alone
    times = np.asarray(allocate_times(wps, within, t0=t0, initial_velocity=init[1]), dtype=float)
    return _full(_planned(Problem(wps, times, within, init, fin, cors), same, "default", method, opts), bounds)


# s: durations tried for the lead segment of a plan from a moving start, longest first
LEAD_TIMES = (0.5, 0.25, 0.125)


def lead_in(initial: FloatArray, bounds: Bounds, corridor: Polytope | None, longest: float = np.inf,
            ) -> tuple[float, FloatArray] | None:
    """The lead segment of a plan from the moving jet `initial`: its own Taylor curve for tau s
    (the longest of LEAD_TIMES up to `longest` whose certified control points hold the bounds
    and stay in `corridor`), as (tau, the jet it ends with); None when none does.

    Why: one degree-9 segment from a given jet has its first five control points fixed by that
    jet and its duration, and they march outwards as the duration grows (velocity by T, jerk by
    T, snap by T^2 on the acceleration's points...). A long first leg from a jerky or fast state
    (a mission or a timed mission sent in flight) then breaks the acceleration bound or the
    corridor for every duration, and stretching only makes it worse. A knot tau s along the
    vehicle's own motion keeps the first segment short; the knot's jet is free, so the plan can
    turn from there. The Taylor curve itself is one plan of the lead segment: the knot never
    makes a plan infeasible that its lead held."""
    from planner_core.certificate import hull_violation, segment_ctrl

    jet = np.asarray(initial, dtype=float)
    for tau in LEAD_TIMES:
        if tau > longest:
            continue
        end = np.zeros_like(jet)
        for k in range(jet.shape[0]):
            end[k] = sum(jet[i] * tau ** (i - k) / factorial(i - k) for i in range(k, jet.shape[0]))
        ctrl = segment_ctrl(jet, end, tau)
        if hull_violation(ctrl[None], np.array([tau]), bounds, [corridor]) is None:
            return tau, end
    return None


def _fixed_with_lead(wps: FloatArray, bounds: Bounds, within: Bounds, cors: tuple[Polytope | None, ...] | None,
                     given: FloatArray | None, init: FloatArray, fin: FloatArray, t0: float, method: str,
                     opts: dict[str, Any]) -> MissionPlan | None:
    """`_fixed` once more with a knot on the vehicle's own motion a short lead time after the
    start (`lead_in`); the knot splits the first leg (its given duration is shared) and is no
    given waypoint (`waypoint_index` skips it). None when no lead holds."""
    first = None if cors is None else cors[0]
    lead = lead_in(init, bounds if given is not None else within, first,
                   np.inf if given is None else 0.5 * float(given[0]))
    if lead is None:
        return None
    tau, end = lead
    points = np.vstack([wps[0], end[0], wps[1:]])
    lead_cors = None if cors is None else (first, *cors)
    if given is not None:
        mp = _fixed(points, bounds, within, lead_cors, np.concatenate([[tau, given[0] - tau], given[1:]]), init, fin,
                    t0, method, opts)
    else:
        from planner_core.timing import allocate_times

        rest = np.asarray(allocate_times(points[1:], within, t0=t0 + tau, initial_velocity=end[1]), dtype=float)
        planned = _planned(Problem(points, np.concatenate([[t0], rest]), within, init, fin, lead_cors),
                           np.arange(points.shape[0], dtype=np.int64), "default", method, opts)
        mp = _full(planned, bounds)
    index = np.concatenate([[0], np.arange(2, points.shape[0])]).astype(np.int64)
    return replace(mp, waypoint_index=index)


def _full(mp: MissionPlan, bounds: Bounds) -> MissionPlan:
    """The plan found within the reserve, as a problem with the full bounds (what replans get).
    Not verified again: `_checked` verified it within the reserve, which the full bounds contain."""
    if mp.problem.bounds is bounds:
        return mp
    return replace(mp, problem=replace(mp.problem, bounds=bounds))


def _jet(jet: ArrayLike | None, position: FloatArray, name: str) -> FloatArray:
    from planner_core.problem import rest_jet

    if jet is None:
        return rest_jet(position)
    out = np.array(jet, dtype=float)
    if out.shape != (5, 3) or not np.all(np.isfinite(out)):
        raise FieldError(name, f"expected a finite (5, 3) jet (position .. snap), got shape {out.shape}")
    if np.linalg.norm(out[0] - position) > 1e-9 * (1.0 + np.linalg.norm(position)):
        raise FieldError(f"{name}[0]", f"position {out[0].tolist()} is not the waypoint {position.tolist()}")
    return out


def _planned(problem: Problem, index: IntArray, mode: str, method: str, opts: dict[str, Any]) -> MissionPlan:
    res = plan(problem, method, **opts)
    traj = res.trajectory
    # the planner's recovery may have stretched durations: the planned problem is at its times
    planned = problem if traj is None or np.array_equal(traj.times, problem.times) else replace(problem,
                                                                                                times=traj.times)
    return _checked(MissionPlan(res, planned, index, mode))


def _checked(mp: MissionPlan) -> MissionPlan:
    """Verify the answer once more against the problem it claims (plan verified it already):
    a result handed to an autopilot is never trusted on one check alone."""
    traj = mp.result.trajectory
    if not mp.result.ok or traj is None:
        return mp
    problem = mp.problem if np.array_equal(traj.times, mp.problem.times) else replace(mp.problem, times=traj.times)
    report = verify(traj, problem)
    if report.ok:
        return replace(mp, problem=problem)
    failed = replace(mp.result, status=PlanStatus.INFEASIBLE, trajectory=None,
                     message="verification failed: " + report.summary())
    return replace(mp, result=failed, problem=problem)
