"""Which bound binds, and the smallest uniform duration scale that plans.

When the given durations are infeasible, `scale_search` plans the problem with
every duration multiplied by one factor s (times t0 + s (t - t0)), each
candidate planned without recovery and verified by `plan`, doubling s from 1
until a plan holds (at most `MAX_SCALE`), then bisecting to a relative
`SCALE_TOL`. The answer is the smallest feasible scale found (the plan at it
is returned too), under the assumption, true for a single segment and in
practice for the receding window, that a plan feasible at s stays feasible at
larger s. `binding_bound` names the constraint the plan at that scale uses most
of, i.e. the one that binds first when the durations shrink: order, axis,
segment, and the waypoints the segment joins (indices into the problem's
waypoints, as the user gave them).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from planner_core.constraints import certified_points
from planner_core.problem import ORDER_NAMES, FloatArray, Problem, Trajectory

MAX_SCALE = 64.0
SCALE_TOL = 0.005  # relative width of the final bracket
_TIE = 1e-3  # usages this close to the largest are named as candidates too

__all__ = ["Binding", "ScaleSearch", "binding_bound", "bound_usage", "norm_usage", "scale_search", "scaled"]


@dataclass(frozen=True)
class Binding:
    """The constraint a plan uses most of (usage 1 = exactly at the bound)."""

    kind: str  # "bounds" | "corridor"
    segment: int
    waypoints: tuple[int, int]  # the waypoints the segment joins, as given
    usage: float  # fraction of the bound the certificate uses (corridor: 1 at a face)
    order: int | None = None  # 1..4 for bounds
    axis: int | None = None  # 0..2 for box bounds; None for the horizontal norm
    side: str | None = None  # "max" | "min" | "norm" (the horizontal norm bound, on its polygon)
    candidates: tuple[str, ...] = ()  # other constraints within a hair of the same usage

    def describe(self) -> str:
        where = f"segment {self.segment} (waypoint {self.waypoints[0]} -> {self.waypoints[1]})"
        if self.kind == "bounds" and self.side == "norm" and self.order is not None:
            return f"horizontal {ORDER_NAMES[self.order]} norm in {where}"
        if self.kind == "corridor" or self.order is None or self.axis is None:
            return f"corridor of {where}"
        return f"{ORDER_NAMES[self.order]} {self.side} on axis {'xyz'[self.axis]} in {where}"

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "segment": self.segment,
            "waypoints": list(self.waypoints),
            "order": self.order,
            "order_name": None if self.order is None else ORDER_NAMES[self.order],
            "axis": None if self.axis is None else "xyz"[self.axis],
            "side": self.side,
            "usage": self.usage,
            "candidates": list(self.candidates),
        }


@dataclass(frozen=True)
class ScaleSearch:
    """Outcome of `scale_search`: the smallest feasible scale found (None: none up to MAX_SCALE)."""

    scale: float | None
    infeasible_below: float  # the largest scale tried that did not plan
    plans: int  # candidates planned (each verified)
    binding: Binding | None
    result: Any = None  # the PlanResult at `scale` (OK), else None

    def to_dict(self) -> dict[str, Any]:
        return {
            "min_scale": self.scale,
            "infeasible_below": self.infeasible_below,
            "plans": self.plans,
            "binding": None if self.binding is None else self.binding.to_dict(),
        }


def scaled(problem: Problem, factor: float) -> Problem:
    """The problem with every duration multiplied by `factor` (start time kept)."""
    t0 = problem.times[0]
    return replace(problem, times=t0 + factor * (problem.times - t0))


def bound_usage(traj: Trajectory, problem: Problem) -> tuple[FloatArray, FloatArray]:
    """Per segment, order 1..4 and axis, the certificate's use of the upper and lower bound.

    (s, 4, 3) arrays: max over the certified points (the control points of the hodograph's
    subdivided pieces, as the planner and `verify` certify them) of value / hi (for hi > 0)
    and value / lo (for lo < 0); 0 where the bound is absent or of the other sign.
    """
    ctrl = traj.control_points
    d = np.diff(traj.times)
    s = ctrl.shape[0]
    up = np.zeros((s, 4, 3))
    dn = np.zeros((s, 4, 3))
    hi, lo = problem.bounds.hi, problem.bounds.lo
    for k in range(1, 5):
        h = certified_points(ctrl, k, d)  # (s, points, 3)
        top, bot = h.max(axis=1), h.min(axis=1)
        hk, lk = hi[k - 1], lo[k - 1]
        with np.errstate(divide="ignore", invalid="ignore"):
            up[:, k - 1] = np.where(np.isfinite(hk) & (hk > 0), top / np.where(hk > 0, hk, 1.0), 0.0)
            dn[:, k - 1] = np.where(np.isfinite(lk) & (lk < 0), bot / np.where(lk < 0, lk, -1.0), 0.0)
    return up, dn


def norm_usage(traj: Trajectory, problem: Problem) -> FloatArray:
    """(s, 4) per segment and order, the certificate's use of the horizontal norm bound: the
    largest max_i |n_i . c| / (r cos(pi / N)) over the certified points (1 = on the polygon);
    0 where there is no norm bound."""
    from planner_core.constraints import polygon_normals

    ctrl = traj.control_points
    d = np.diff(traj.times)
    out = np.zeros((ctrl.shape[0], 4))
    b = problem.bounds
    for k in range(1, 5):
        lim = float(b.polygon_radius[k - 1])
        if not np.isfinite(lim):
            continue
        h = certified_points(ctrl, k, d)  # (s, points, 3)
        out[:, k - 1] = np.abs(h[..., :2] @ polygon_normals(b.sides).T).max(axis=(1, 2)) / lim
    return out


def _corridor_usage(traj: Trajectory, problem: Problem) -> FloatArray:
    """(s,) 1 - (smallest face slack of the control points) / (corridor size); 0 without one."""
    out = np.zeros(traj.n_segments)
    for s in range(traj.n_segments):
        poly = problem.corridor(s)
        if poly is None or poly.A.shape[0] == 0:
            continue
        slack = poly.b[None, :] - traj.control_points[s] @ poly.A.T  # (10, faces)
        size = max(1e-9, float(np.max(np.abs(poly.b))))
        out[s] = 1.0 - max(float(np.min(slack)), 0.0) / size
    return out


def binding_bound(traj: Trajectory, problem: Problem) -> Binding | None:
    """The constraint the trajectory's certificate uses most of (see module docstring).

    A corridor is named only when a control point sits on one of its faces (slack below
    1e-6 of its size) and no derivative bound is used to within SCALE_TOL.
    """
    if traj.n_segments == 0:
        return None
    up, dn = bound_usage(traj, problem)
    both = np.stack([up, dn])  # (2, s, 4, 3)
    best = float(both.max())
    norms = norm_usage(traj, problem) if problem.bounds.has_norm else np.zeros((traj.n_segments, 4))
    corr = _corridor_usage(traj, problem)
    if max(best, float(norms.max())) < 1.0 - 2 * SCALE_TOL and corr.size and float(corr.max()) > 1.0 - 1e-6:
        seg = int(np.argmax(corr))
        return Binding("corridor", seg, (seg, seg + 1), float(corr[seg]))
    if float(norms.max()) > best:
        seg, k = (int(i) for i in np.unravel_index(int(np.argmax(norms)), norms.shape))
        return Binding("bounds", seg, (seg, seg + 1), float(norms[seg, k]), k + 1, None, "norm")
    if best <= 0.0:
        return None
    side, seg, k, ax = (int(i) for i in np.unravel_index(int(np.argmax(both)), both.shape))
    names = []
    for sd, sg, kk, aa in np.argwhere(both >= best - _TIE):
        if (sd, sg, kk, aa) != (side, seg, k, ax):
            names.append(f"{ORDER_NAMES[kk + 1]} {'max' if sd == 0 else 'min'} on axis {'xyz'[aa]}"
                         f" in segment {sg}")
    return Binding("bounds", seg, (seg, seg + 1), best, k + 1, ax, "max" if side == 0 else "min",
                   tuple(names[:8]))


def scale_search(
    problem: Problem,
    plan_at: Callable[[Problem], Any],
    *,
    start: float = 1.0,
    max_scale: float = MAX_SCALE,
    tol: float = SCALE_TOL,
) -> ScaleSearch:
    """Smallest uniform duration scale in (start, max_scale] whose plan holds (module docstring).

    `plan_at(problem)` returns a PlanResult (planned and verified; `.ok`). `start` is
    taken as infeasible (it has just failed).
    """
    plans = 0
    lo, hi = start, start
    good = None
    while hi < max_scale:
        hi = min(2.0 * hi, max_scale)
        res = plan_at(scaled(problem, hi))
        plans += 1
        if res.ok:
            good = res
            break
        lo = hi
    if good is None:
        return ScaleSearch(None, lo, plans, None)
    while hi / lo > 1.0 + tol:
        mid = float(np.sqrt(lo * hi))
        res = plan_at(scaled(problem, mid))
        plans += 1
        if res.ok:
            hi, good = mid, res
        else:
            lo = mid
    binding = binding_bound(good.trajectory, scaled(problem, hi)) if good.trajectory is not None else None
    return ScaleSearch(float(hi), float(lo), plans, binding, good)
