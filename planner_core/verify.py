"""The certificate a trajectory needs before it flies.

Checks, each with the place of its worst case:
- waypoints: position at each waypoint time equals the waypoint (absolute);
- boundary jets: the jets at the start and end equal the problem's initial and
  final jets (absolute);
- continuity: C^4 at each junction, relative to the size of the derivative;
- bounds by hull: every hodograph control point of orders 1..4 inside the
  bounds (this is the guarantee: it implies the bound in continuous time);
- bounds by sampling: dense samples of orders 1..4 (an independent check);
- corridors by hull (all 10 control points) and by sampling.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from planner_core.bezier import bernstein_basis, end_jet, falling, hodographs, start_jet
from planner_core.problem import DEGREE, ORDER_NAMES, FloatArray, Problem, Trajectory

SAMPLES_PER_SEGMENT = 64


@dataclass(frozen=True)
class Worst:
    value: float  # violation (> 0 is bad) or error
    segment: int | None = None
    order: int | None = None
    axis: int | None = None
    time: float | None = None


@dataclass(frozen=True)
class VerifyReport:
    ok: bool
    tol: float
    continuity_tol: float
    waypoint_error: Worst
    boundary_error: Worst
    continuity_error: Worst  # relative; segment = index of the junction's waypoint
    bound_violation_hull: Worst
    bound_violation_sampled: Worst
    corridor_violation_hull: Worst
    corridor_violation_sampled: Worst
    structure_error: str = ""

    def failures(self) -> list[str]:
        out = []
        if self.structure_error:
            out.append(self.structure_error)
        for name in ("waypoint_error", "boundary_error", "bound_violation_hull", "bound_violation_sampled",
                     "corridor_violation_hull", "corridor_violation_sampled"):
            w: Worst = getattr(self, name)
            if w.value > self.tol:
                out.append(f"{name} {w.value:.3g}{_where(w)}")
        if self.continuity_error.value > self.continuity_tol:
            out.append(f"continuity_error {self.continuity_error.value:.3g}{_where(self.continuity_error)}")
        return out

    def summary(self) -> str:
        head = "OK" if self.ok else "FAILED: " + "; ".join(self.failures())
        lines = [f"verify: {head}"]
        for name in ("waypoint_error", "boundary_error", "continuity_error", "bound_violation_hull",
                     "bound_violation_sampled", "corridor_violation_hull", "corridor_violation_sampled"):
            w = getattr(self, name)
            lines.append(f"  {name:28s} {w.value: .3e}{_where(w)}")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["failures"] = self.failures()
        out: dict[str, Any] = _finite(d)
        return out


def _finite(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list):
        return [_finite(v) for v in obj]
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    return obj


def _where(w: Worst) -> str:
    parts = []
    if w.segment is not None:
        parts.append(f"segment {w.segment}")
    if w.order is not None:
        parts.append(f"order {w.order} ({ORDER_NAMES[w.order]})")
    if w.axis is not None:
        parts.append(f"axis {'xyz'[w.axis]}")
    if w.time is not None:
        parts.append(f"t={w.time:.4g}")
    return f" at {', '.join(parts)}" if parts else ""


def _none() -> Worst:
    return Worst(-np.inf)


def verify(traj: Trajectory, problem: Problem, tol: float = 1e-9, continuity_tol: float = 1e-6) -> VerifyReport:
    structure = _structure(traj, problem)
    if structure:
        nan = Worst(np.inf)
        return VerifyReport(False, tol, continuity_tol, nan, nan, nan, nan, nan, nan, nan, structure)
    ctrl = traj.control_points
    d = np.diff(traj.times)
    wp = _waypoints(traj, problem)
    bnd = _boundary(traj, problem)
    cont = _continuity(ctrl, d)
    bh, bs = _bounds(ctrl, d, traj.times, problem)
    ch, cs = _corridors(ctrl, traj.times, problem)
    checks = [wp, bnd, bh, bs, ch, cs]
    ok = all(w.value <= tol for w in checks) and cont.value <= continuity_tol
    return VerifyReport(ok, tol, continuity_tol, wp, bnd, cont, bh, bs, ch, cs)


def _structure(traj: Trajectory, problem: Problem) -> str:
    ctrl = traj.control_points
    if ctrl.ndim != 3 or ctrl.shape[1:] != (DEGREE + 1, 3):
        return f"control_points: shape {ctrl.shape}, expected (s, {DEGREE + 1}, 3)"
    if ctrl.shape[0] != problem.m - 1 or traj.times.shape != (problem.m,):
        return f"segments: trajectory has {ctrl.shape[0]} segments, problem has {problem.m - 1}"
    if not np.all(np.isfinite(ctrl)) or not np.all(np.isfinite(traj.times)):
        return "control_points: non-finite values"
    if not np.all(np.diff(traj.times) > 0):
        return "times: not strictly increasing"
    terr = float(np.max(np.abs(traj.times - problem.times)))
    if terr > 1e-9 * (1.0 + float(np.max(np.abs(problem.times)))):
        return f"times: differ from the problem's by {terr:.3g} s"
    return ""


def _waypoints(traj: Trajectory, problem: Problem) -> Worst:
    ctrl = traj.control_points
    pts = np.concatenate([ctrl[:, 0], ctrl[-1:, -1]])
    # the end of segment j-1 must equal the start of segment j too: both are checked
    ends = np.concatenate([ctrl[:1, 0], ctrl[:, -1]])
    err = np.maximum(np.abs(pts - problem.waypoints), np.abs(ends - problem.waypoints)).max(axis=1)
    i = int(np.argmax(err))
    return Worst(float(err[i]), segment=min(i, traj.n_segments - 1), time=float(traj.times[i]))


def _boundary(traj: Trajectory, problem: Problem) -> Worst:
    d = np.diff(traj.times)
    e0 = np.abs(start_jet(traj.control_points[0], d[0]) - problem.initial)
    e1 = np.abs(end_jet(traj.control_points[-1], d[-1]) - problem.final)
    if e0.max() >= e1.max():
        k, a = np.unravel_index(int(np.argmax(e0)), e0.shape)
        return Worst(float(e0.max()), 0, int(k), int(a), traj.t0)
    k, a = np.unravel_index(int(np.argmax(e1)), e1.shape)
    return Worst(float(e1.max()), traj.n_segments - 1, int(k), int(a), traj.t_end)


def _continuity(ctrl: FloatArray, d: FloatArray) -> Worst:
    if ctrl.shape[0] < 2:
        return _none()
    worst = Worst(0.0)
    # Stored control points carry rounding of eps*|P|; a k-th difference scaled by
    # n!/(n-k)!/D^k amplifies it, so far from the origin (long missions) the exact
    # junction match is only good to that floor. Errors above the floor still count.
    size = np.max(np.abs(ctrl), axis=1)  # (s, 3)
    pair = np.maximum(size[:-1], size[1:])
    dmin = np.minimum(d[:-1], d[1:])[:, None]
    for k in range(5):
        if k == 0:
            left, right = ctrl[:-1, -1], ctrl[1:, 0]
        else:
            left = hodographs(ctrl[:-1], k, d[:-1])[:, -1]
            right = hodographs(ctrl[1:], k, d[1:])[:, 0]
        floor = 64.0 * np.finfo(float).eps * pair * 2.0**k * falling(DEGREE, k) / dmin**k
        scale = 1.0 + np.maximum(np.abs(left), np.abs(right))
        rel = np.maximum(np.abs(left - right) - floor, 0.0) / scale
        j, a = np.unravel_index(int(np.argmax(rel)), rel.shape)
        if rel[j, a] > worst.value:
            worst = Worst(float(rel[j, a]), int(j) + 1, k, int(a))
    return worst


def _bounds(ctrl: FloatArray, d: FloatArray, times: FloatArray, problem: Problem) -> tuple[Worst, Worst]:
    lo, hi = problem.bounds.lo, problem.bounds.hi
    hull = Worst(-np.inf)
    samp = Worst(-np.inf)
    u = np.linspace(0.0, 1.0, SAMPLES_PER_SEGMENT)
    for k in range(1, 5):
        pts = hodographs(ctrl, k, d)  # (s, 10-k, 3)
        v = np.maximum(pts - hi[k - 1], lo[k - 1] - pts)
        s, i, a = np.unravel_index(int(np.argmax(v)), v.shape)
        if v[s, i, a] > hull.value:
            hull = Worst(float(v[s, i, a]), int(s), k, int(a))
        vals = np.einsum("ti,sid->std", bernstein_basis(DEGREE - k, u), pts)
        v = np.maximum(vals - hi[k - 1], lo[k - 1] - vals)
        s, t, a = np.unravel_index(int(np.argmax(v)), v.shape)
        if v[s, t, a] > samp.value:
            samp = Worst(float(v[s, t, a]), int(s), k, int(a), float(times[s] + u[t] * d[s]))
    return hull, samp


def _corridors(ctrl: FloatArray, times: FloatArray, problem: Problem) -> tuple[Worst, Worst]:
    hull = _none()
    samp = _none()
    if problem.corridors is None:
        return hull, samp
    u = np.linspace(0.0, 1.0, SAMPLES_PER_SEGMENT)
    basis = bernstein_basis(DEGREE, u)
    for s, poly in enumerate(problem.corridors):
        if poly is None or poly.A.shape[0] == 0:
            continue
        vh = poly.violation(ctrl[s])
        if vh > hull.value:
            hull = Worst(vh, s)
        pts = basis @ ctrl[s]
        viol = (pts @ poly.A.T - poly.b).max(axis=1)
        t = int(np.argmax(viol))
        if viol[t] > samp.value:
            samp = Worst(float(viol[t]), s, time=float(times[s] + u[t] * (times[s + 1] - times[s])))
    return hull, samp
