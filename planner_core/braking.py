"""A verified stop: two degree-9 segments from the current jet to rest.

The end jet is rest at an unknown position p (the last five control points
all equal p). A single segment cannot absorb the current jerk and snap: its
first five control points are fixed by the current jet and spread with the
duration cubed, so a second, short, leading segment with a free junction jet
(position included) takes them out first. The QP (integrated squared snap
plus a small pull of p towards the current position) constrains every
certified hodograph point (`constraints.HULL_PIECES` pieces) of both segments within the bounds and every control point
(the junction included) inside the corridor. Total durations are tried
shortest first along a short geometric sequence starting from the time a
bang-bang stop would need; the first solution that passes `verify` is
returned.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from planner_core.bezier import segments_from_jets
from planner_core.constraints import polygon_excess
from planner_core.localqp import solve_local
from planner_core.problem import (
    JET_ORDER,
    ORDER_NAMES,
    Bounds,
    FloatArray,
    Polytope,
    Problem,
    Trajectory,
    rest_jet,
)
from planner_core.result import PlanResult, PlanStatus

STOP_PULL = 1e-3  # weight of |p - p0|^2 against the normalised snap cost
GROWTH = 1.5
N_TRIES = 8
LEADS = (0.25, 0.08)  # shares of the total duration given to the leading segment, tried in turn


def _infeasible(message: str, **stats: object) -> PlanResult:
    return PlanResult(PlanStatus.INFEASIBLE, None, message, None, dict(stats))


def stop_time_scale(velocity: FloatArray, acceleration: FloatArray, bounds: Bounds) -> float:
    """|v| / a_max (braking) plus |a| / j_max (unwinding the current acceleration), on the worst
    axis of the worst of the states (n, 3) or (3,): the time scale of a stop from them."""

    lo, hi = bounds.axis_limits()

    def limit(lim: FloatArray) -> FloatArray:
        return np.where(np.isfinite(lim) & (lim > 0), lim, np.inf)

    v, a = np.atleast_2d(velocity), np.atleast_2d(acceleration)
    t_axis = np.abs(v) / limit(np.minimum(-lo[1], hi[1])) + np.abs(a) / limit(np.minimum(-lo[2], hi[2]))
    # a horizontal norm bound: the horizontal speed brakes at the norm's rate, not each axis's
    r = limit(bounds.horizontal)
    t_h = np.hypot(v[:, 0], v[:, 1]) / r[1] + np.hypot(a[:, 0], a[:, 1]) / r[2]
    return float(max(np.max(t_axis), np.max(t_h)))


def _first_duration(jet: FloatArray, bounds: Bounds) -> float:
    """A lower estimate of the stopping time, at least 0.2 s."""
    return float(max(0.2, 1.2 * stop_time_scale(jet[1], jet[2], bounds)))


def _try(
    jet: FloatArray, bounds: Bounds, corridor: Polytope | None, t0: float, d: float, lead: float
) -> tuple[Trajectory, float] | str:
    """One total duration: the verified two-segment stop, or the reason it failed."""
    from planner_core.verify import verify

    p0 = jet[0]
    dur = {0: lead * d, 1: (1.0 - lead) * d}
    free = {1: np.ones((JET_ORDER, 3), dtype=bool), 2: np.zeros((JET_ORDER, 3), dtype=bool)}
    free[2][0] = True
    n = 18  # junction jet (15) then stop position (3)
    pull_p = np.zeros((n, n))
    pull_q = np.zeros(n)
    pull_p[15:, 15:] = 2.0 * STOP_PULL * np.eye(3)
    pull_q[15:] = -2.0 * STOP_PULL * p0
    rows = None
    if corridor is not None and corridor.A.shape[0]:
        g = np.zeros((corridor.A.shape[0], n))
        g[:, :3] = corridor.A  # the junction point itself (segments constrain P^1..P^8 only)
        rows = (g, np.full(corridor.A.shape[0], -1e30), corridor.b)
    guess = {0: jet, 1: rest_jet(p0), 2: rest_jet(p0)}
    sol = solve_local(
        guess, dur, bounds, lambda _s: corridor, [0, 1], free, extra_cost=(pull_p, pull_q), extra_rows=rows
    )
    if not sol.ok:
        return sol.message
    jets = np.stack([jet, sol.jets[1], sol.jets[2]])
    durations = np.array([dur[0], dur[1]])
    ctrl = segments_from_jets(jets, durations)
    corr = (corridor, corridor)
    times = t0 + np.concatenate([[0.0], np.cumsum(durations)])
    traj = Trajectory(times, ctrl, corr)
    problem = Problem(jets[:, 0].copy(), times.copy(), bounds, jet, jets[2], corr)
    report = verify(traj, problem)
    if not report.ok:
        return f"certificate failed: {report.summary()}"
    return traj, sol.qp_time


def braking_trajectory(
    jet: FloatArray,
    bounds: Bounds,
    corridor: Polytope | Sequence[Polytope | None] | None = None,
    t0: float = 0.0,
    *,
    durations: Sequence[float] | None = None,
) -> PlanResult:
    """From `jet` (5, 3) at time t0 to rest, inside `corridor` and `bounds`; verified.

    `corridor` may be a sequence of candidate regions (e.g. the current
    segment's corridor, then the next one's: near a turn the vehicle is often
    in both and only the next leaves room to stop); those that contain the
    vehicle are tried in order. INFEASIBLE (with the reason) when the vehicle
    is outside every candidate, its current derivatives already exceed the
    bounds, or no tried duration works.
    """
    jet = np.asarray(jet, dtype=float)
    if jet.shape != (JET_ORDER, 3) or not np.all(np.isfinite(jet)):
        raise ValueError(f"jet: expected a finite (5, 3) array, got shape {jet.shape}")
    p0 = jet[0]
    candidates = [corridor] if corridor is None or isinstance(corridor, Polytope) else list(corridor)
    inside = [i for i, c in enumerate(candidates) if c is None or c.A.shape[0] == 0 or c.violation(p0) <= 1e-9]
    if not inside:
        gap = min(c.violation(p0) for c in candidates if c is not None) if candidates else float("nan")
        where = "the corridor" if len(candidates) == 1 else f"all {len(candidates)} corridors"
        return _infeasible(f"vehicle at {p0.tolist()} is outside {where} (by {gap:.3g} m)")
    for k in range(1, JET_ORDER):
        excess = np.maximum(jet[k] - bounds.hi[k - 1], bounds.lo[k - 1] - jet[k])
        if np.any(excess > 1e-9):
            axis = int(np.argmax(excess))
            return _infeasible(
                f"current {ORDER_NAMES[k]} on axis {axis} ({jet[k, axis]:.4g}) is already outside its bounds"
            )
        r = float(bounds.horizontal[k - 1])
        if np.isfinite(r) and float(polygon_excess(jet[k], r, bounds.sides)) > 1e-9:
            # the stop's first hodograph point is this derivative: it must be in the certified polygon
            return _infeasible(
                f"current horizontal {ORDER_NAMES[k]} ({float(np.hypot(jet[k, 0], jet[k, 1])):.4g}) is already "
                f"outside the polygon that certifies its norm bound {r:.4g} (radius {r:.4g} x cos(pi/{bounds.sides}))"
            )
    tries = list(durations) if durations is not None else [
        _first_duration(jet, bounds) * GROWTH**i for i in range(N_TRIES)
    ]
    reasons = []
    for c_index in inside:
        res = _shortest(jet, bounds, candidates[c_index], t0, tries)
        if isinstance(res, PlanResult):
            res.stats["corridor_candidate"] = c_index
            return res
        reasons.append(res if len(inside) == 1 else f"corridor candidate {c_index}: {res}")
    return _infeasible(
        f"no braking trajectory within {len(tries)} durations up to {max(tries):.3g} s: {'; '.join(reasons)}",
        tried=tries,
    )


def _shortest(
    jet: FloatArray, bounds: Bounds, corridor: Polytope | None, t0: float, tries: Sequence[float]
) -> PlanResult | str:
    """The shortest verified stop in `corridor` over the tried durations, or the last reason."""
    reason = "no duration tried"
    for d in tries:
        res: tuple[Trajectory, float] | str = "not tried"
        for lead in LEADS:
            res = _try(jet, bounds, corridor, t0, float(d), lead)
            if not isinstance(res, str):
                break
        if isinstance(res, str):
            reason = f"duration {d:.3g} s: {res}"
            continue
        traj, qp_time = res
        stop = traj.control_points[-1, -1]
        stats = {"duration": float(d), "tried": list(tries[: list(tries).index(d) + 1]), "stop": stop.tolist(),
                 "distance": float(np.linalg.norm(stop - jet[0])), "qp_time_s": qp_time}
        traj = Trajectory(traj.times, traj.control_points, traj.corridors, dict(stats))
        return PlanResult(PlanStatus.OK, traj, f"stop in {d:.3g} s at {np.round(stop, 3).tolist()}", None, stats)
    return reason
