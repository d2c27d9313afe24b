"""The certificate a trajectory needs before it flies.

Checks, each with the place of its worst case:
- waypoints: position at each waypoint time equals the waypoint (absolute);
- boundary jets: the jets at the start and end equal the problem's initial and
  final jets (absolute);
- continuity: C^4 at each junction, relative to the size of the derivative;
- bounds by hull: the control points of the `constraints.HULL_PIECES` de Casteljau
  pieces of every hodograph of orders 1..4 inside the bounds (the planner's own rows;
  this is the guarantee: it implies the bound in continuous time);
- bounds by sampling: dense samples of orders 1..4 (an independent check);
- a horizontal norm bound (`Bounds.horizontal`), where there is one: the same certified points
  inside the polygon inscribed in its disc (the guarantee), and the samples' norm (a check); the
  report gives the largest sampled norm per order (`horizontal_peak`);
- corridors by hull (all 10 control points) and by sampling.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from functools import cache
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planner_core.bezier import bernstein_basis, end_jet, falling, stacked_pieces, start_jet
from planner_core.constraints import HULL_PIECES
from planner_core.problem import DEGREE, ORDER_NAMES, FloatArray, Polytope, Problem, Trajectory

SAMPLES_PER_SEGMENT = 64
# block sizes that keep sampling temporaries at 100-200 kB (cache sized, no page faults)
_SEGMENT_BLOCK = 128
_ROW_BLOCK = 240


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
    # the horizontal norm bound (Bounds.horizontal), where there is one: the certified points
    # outside the polygon that certifies it (the guarantee), the samples' norm over the bound
    # (an independent check), and the largest sampled norm per order 1..4 (None: no norm bound)
    norm_violation_hull: Worst = field(default_factory=lambda: Worst(-np.inf))
    norm_violation_sampled: Worst = field(default_factory=lambda: Worst(-np.inf))
    horizontal_peak: tuple[float, float, float, float] | None = None

    def failures(self) -> list[str]:
        out = []
        if self.structure_error:
            out.append(self.structure_error)
        for name in ("waypoint_error", "boundary_error", "bound_violation_hull", "bound_violation_sampled",
                     "norm_violation_hull", "norm_violation_sampled", "corridor_violation_hull",
                     "corridor_violation_sampled"):
            w: Worst = getattr(self, name)
            if w.value > self.tol:
                out.append(f"{name} {w.value:.3g}{_where(w)}")
        if self.continuity_error.value > self.continuity_tol:
            out.append(f"continuity_error {self.continuity_error.value:.3g}{_where(self.continuity_error)}")
        return out

    def summary(self) -> str:
        head = "OK" if self.ok else "FAILED: " + "; ".join(self.failures())
        lines = [f"verify: {head}"]
        names = ["waypoint_error", "boundary_error", "continuity_error", "bound_violation_hull",
                 "bound_violation_sampled", "corridor_violation_hull", "corridor_violation_sampled"]
        if self.horizontal_peak is not None:
            names[5:5] = ["norm_violation_hull", "norm_violation_sampled"]
        for name in names:
            w = getattr(self, name)
            lines.append(f"  {name:28s} {w.value: .3e}{_where(w)}")
        if self.horizontal_peak is not None:
            peaks = ", ".join(f"{ORDER_NAMES[k + 1]} {v:.4g}" for k, v in enumerate(self.horizontal_peak)
                              if np.isfinite(v))
            lines.append(f"  {'horizontal_peak':28s} {peaks}")
        return "\n".join(lines)

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["failures"] = self.failures()
        out: dict[str, Any] = _finite(d)
        return out


def _finite(obj: Any) -> Any:
    if isinstance(obj, dict):
        return {k: _finite(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
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


def verify(traj: Trajectory, problem: Problem, tol: float = 1e-9, continuity_tol: float = 1e-6,
           pieces: int = HULL_PIECES) -> VerifyReport:
    """The certificate (module docstring). `pieces`: de Casteljau pieces per hodograph the
    bounds are certified on (`bezier.stacked_pieces`); the default is the planner's own, 1 is
    the plain hull (stricter: plans that use the bounds fully fail it)."""
    if pieces < 1:
        raise ValueError(f"pieces: must be >= 1, got {pieces}")
    structure = _structure(traj, problem)
    if structure:
        nan = Worst(np.inf)
        return VerifyReport(False, tol, continuity_tol, nan, nan, nan, nan, nan, nan, nan, structure)
    ctrl = traj.control_points
    d = np.diff(traj.times)
    wp = _waypoints(traj, problem)
    bnd = _boundary(traj, problem)
    hods = _hodograph_stack(ctrl, d)
    cont = _continuity(hods, d)
    bh, bs = _bounds(hods, d, traj.times, problem, pieces)
    ch, cs = _corridors(ctrl, traj.times, problem)
    checks = [wp, bnd, bh, bs, ch, cs]
    if not problem.bounds.has_norm:
        ok = all(w.value <= tol for w in checks) and cont.value <= continuity_tol
        return VerifyReport(ok, tol, continuity_tol, wp, bnd, cont, bh, bs, ch, cs)
    nh, ns, peak = _norms(hods, d, traj.times, problem, pieces)
    ok = all(w.value <= tol for w in [*checks, nh, ns]) and cont.value <= continuity_tol
    return VerifyReport(ok, tol, continuity_tol, wp, bnd, cont, bh, bs, ch, cs,
                        norm_violation_hull=nh, norm_violation_sampled=ns, horizontal_peak=peak)


def _norms(hods: list[FloatArray], d: FloatArray, times: FloatArray, problem: Problem,
           pieces: int) -> tuple[Worst, Worst, tuple[float, float, float, float]]:
    """The horizontal norm bound: certified points against its polygon (the guarantee: inside the
    polygon is inside the disc), dense samples' norm against the bound, the largest sampled norm
    per order (nan where not bounded)."""
    from planner_core.constraints import polygon_excess

    b = problem.bounds
    u = _sample_params(SAMPLES_PER_SEGMENT)
    hull, samp = Worst(-np.inf), Worst(-np.inf)
    peak = [float("nan")] * 4
    for k in range(1, 5):
        r = float(b.horizontal[k - 1])
        if not np.isfinite(r):
            continue
        cert = _pieces(hods[k], pieces)  # (points, s, 3)
        ex = polygon_excess(cert, r, b.sides).max(axis=0)  # (s,)
        i = int(np.argmax(ex))
        if ex[i] > hull.value:
            hull = Worst(float(ex[i]), i, k)
        pts = hods[k]  # (n, s, 3): one matmul for every segment's samples, as `_sample_extremes`
        vals = (_sample_basis(DEGREE - k, SAMPLES_PER_SEGMENT) @ pts.reshape(pts.shape[0], -1)).reshape(-1, *pts.shape[1:])
        norm = np.hypot(vals[..., 0], vals[..., 1])  # (samples, s)
        t, sg = np.unravel_index(int(np.argmax(norm)), norm.shape)
        peak[k - 1] = float(norm[t, sg])
        if norm[t, sg] - r > samp.value:
            samp = Worst(float(norm[t, sg] - r), int(sg), k, time=float(times[sg] + u[t] * d[sg]))
    return hull, samp, (peak[0], peak[1], peak[2], peak[3])



def _same_polytope(a: Polytope | None, b: Polytope | None) -> bool:
    if a is b:
        return True
    if a is None or b is None:
        return False
    return a.A.shape == b.A.shape and bool(np.array_equal(a.A, b.A)) and bool(np.array_equal(a.b, b.b))


def verify_changed(
    old_traj: Trajectory, old_problem: Problem, traj: Trajectory, problem: Problem, tol: float = 1e-9
) -> str | None:
    """Verify a local replan of the verified (`old_traj`, `old_problem`) independently of the
    planner's own certificate, but only where it can differ (None if it passes, else why).

    A new segment whose control points and duration are bit-identical to a segment of the
    verified old trajectory, under the same bounds, needs no new bound check: only a corridor
    check when its corridor changed (pop-ups add planes to many corridors). Every other
    segment is verified with `verify` in a window that includes one neighbour on each side,
    so its junctions get verify's continuity check; windows at either end of the trajectory
    check the problem's initial/final jets. Waypoints and times are checked everywhere.
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
    same_bounds = old_problem.bounds.same_as(problem.bounds)
    old_d = np.diff(old_traj.times)
    old_cors = old_problem.corridors or (None,) * old_traj.n_segments
    known: dict[bytes, list[Polytope | None]] = {}
    if same_bounds:
        for s in range(old_traj.n_segments):
            key = old_traj.control_points[s].tobytes() + old_d[s].tobytes()
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
    """The plan's first and last jets against the problem's, each order net of the rounding floor
    of a k-th derivative taken from stored control points (as `_continuity`): a 1000-waypoint
    plan 30 m from the origin ending on a 0.45 s segment carries ~5e-7 of rounding in its final
    snap, which an absolute 1e-9 refused (issue 25's service benchmark)."""
    d = np.diff(traj.times)
    ctrl = traj.control_points
    k = np.arange(5)[:, None]
    scale = 64.0 * np.finfo(float).eps * 2.0**k * np.array([falling(DEGREE, i) for i in range(5)])[:, None]

    def excess(jet_error: FloatArray, seg: FloatArray, dur: float) -> FloatArray:
        floor = scale * float(np.max(np.abs(seg))) / dur**k
        out: FloatArray = np.maximum(jet_error - floor, 0.0)
        out[0] = jet_error[0]  # positions: no derivative, no amplified rounding
        return out

    e0 = excess(np.abs(start_jet(ctrl[0], d[0]) - problem.initial), ctrl[0], float(d[0]))
    e1 = excess(np.abs(end_jet(ctrl[-1], d[-1]) - problem.final), ctrl[-1], float(d[-1]))
    if e0.max() >= e1.max():
        i, a = np.unravel_index(int(np.argmax(e0)), e0.shape)
        return Worst(float(e0.max()), 0, int(i), int(a), traj.t0)
    i, a = np.unravel_index(int(np.argmax(e1)), e1.shape)
    return Worst(float(e1.max()), traj.n_segments - 1, int(i), int(a), traj.t_end)


def _continuity(hods: list[FloatArray], d: FloatArray) -> Worst:
    if hods[0].shape[1] < 2:
        return _none()
    worst = Worst(0.0)
    # Stored control points carry rounding of eps*|P|; a k-th difference scaled by
    # n!/(n-k)!/D^k amplifies it, so far from the origin (long missions) the exact
    # junction match is only good to that floor. Errors above the floor still count.
    size = np.max(np.abs(hods[0]), axis=0)  # (s, 3)
    pair = np.maximum(size[:-1], size[1:])
    dmin = np.minimum(d[:-1], d[1:])[:, None]
    for k in range(5):
        left, right = hods[k][-1, :-1], hods[k][0, 1:]
        floor = 64.0 * np.finfo(float).eps * pair * 2.0**k * falling(DEGREE, k) / dmin**k
        scale = 1.0 + np.maximum(np.abs(left), np.abs(right))
        rel = np.maximum(np.abs(left - right) - floor, 0.0) / scale
        j, a = np.unravel_index(int(np.argmax(rel)), rel.shape)
        if rel[j, a] > worst.value:
            worst = Worst(float(rel[j, a]), int(j) + 1, k, int(a))
    return worst


def _pieces(pts: FloatArray, pieces: int) -> FloatArray:
    """(n+1, s, 3) control points -> (pieces n + 1, s, 3): those of the de Casteljau pieces."""
    if pieces == 1:
        return pts
    n1, s, _ = pts.shape
    sub = stacked_pieces(n1 - 1, pieces)
    out: FloatArray = (sub @ pts.reshape(n1, 3 * s)).reshape(sub.shape[0], s, 3)
    return out


def _bounds(hods: list[FloatArray], d: FloatArray, times: FloatArray, problem: Problem,
            pieces: int = 1) -> tuple[Worst, Worst]:
    lo, hi = problem.bounds.lo, problem.bounds.hi
    u = _sample_params(SAMPLES_PER_SEGMENT)
    hull: tuple[float, int, int] = (-np.inf, 0, 1)  # value, segment, order
    samp: tuple[float, int, int] = (-np.inf, 0, 1)
    cert = [hods[0]] + [_pieces(hods[k], pieces) for k in range(1, 5)]
    for k in range(1, 5):
        pts = hods[k]  # (10-k, s, 3)
        c = cert[k]
        hull = _better(hull, _box_excess(c.max(axis=0), c.min(axis=0), lo[k - 1], hi[k - 1]), k)
        top, bottom = _sample_extremes(_sample_basis(DEGREE - k, SAMPLES_PER_SEGMENT), pts)
        samp = _better(samp, _box_excess(top, bottom, lo[k - 1], hi[k - 1]), k)
    # Only the winning (order, segment) is unravelled, in the same (segment, index,
    # axis) order as an elementwise argmax would pick, so ties resolve as before.
    hv, hs, hk = hull
    _, ha = _first_max(_box_violation(cert[hk][:, hs], lo[hk - 1], hi[hk - 1]))
    sv, ss, sk = samp
    vals = _sample_basis(DEGREE - sk, SAMPLES_PER_SEGMENT) @ hods[sk][:, ss]
    st, sa = _first_max(_box_violation(vals, lo[sk - 1], hi[sk - 1]))
    return (Worst(hv, hs, hk, ha),
            Worst(sv, ss, sk, sa, float(times[ss] + u[st] * d[ss])))


def _sample_extremes(basis: FloatArray, pts: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Largest and smallest sample per (segment, axis) of the curves pts (n, s, 3).

    Blocks of segments keep the (samples, 3*block) temporaries cache sized: one
    whole-trajectory temporary costs more in page faults than the matmul itself.
    """
    n, s, _ = pts.shape
    top = np.empty((s, 3))
    bottom = np.empty((s, 3))
    for a in range(0, s, _SEGMENT_BLOCK):
        z = min(a + _SEGMENT_BLOCK, s)
        vals = basis @ pts[:, a:z].reshape(n, 3 * (z - a))
        top[a:z] = vals.max(axis=0).reshape(z - a, 3)
        bottom[a:z] = vals.min(axis=0).reshape(z - a, 3)
    return top, bottom


def _box_excess(top: FloatArray, bottom: FloatArray, lo: FloatArray, hi: FloatArray) -> FloatArray:
    """Per segment, the largest excess over the box given per-axis extremes (s, 3): (s,).

    fl(x - h) is monotone in x, so max(x) - hi is exactly the max of x - hi:
    reductions first, then differences on the small (s, 3) arrays.
    """
    out: FloatArray = np.maximum(top - hi, lo - bottom).max(axis=1)
    return out


def _box_violation(vals: FloatArray, lo: FloatArray, hi: FloatArray) -> FloatArray:
    out: FloatArray = np.maximum(vals - hi, lo - vals)
    return out


def _better(best: tuple[float, int, int], per_segment: FloatArray, order: int) -> tuple[float, int, int]:
    s = int(np.argmax(per_segment))
    v = float(per_segment[s])
    return (v, s, order) if v > best[0] else best


def _first_max(v: FloatArray) -> tuple[int, int]:
    i, a = np.unravel_index(int(np.argmax(v)), v.shape)
    return int(i), int(a)


def _hodograph_stack(ctrl: FloatArray, d: FloatArray) -> list[FloatArray]:
    """Hodograph control points of orders 0..4 for all segments, each (10-k, s, 3).

    Index-major layout: every per-order sampling is one (samples, 10-k) @ (10-k, 3s)
    matmul.
    """
    out = [np.ascontiguousarray(ctrl.transpose(1, 0, 2))]  # (10, s, 3)
    for k in range(1, 5):
        # the hodograph of a degree-n curve: n / D times the differences of its points
        h = out[-1][1:] - out[-1][:-1]
        h *= ((DEGREE + 1 - k) / d)[None, :, None]
        out.append(h)
    return out


@cache
def _sample_params(n_samples: int) -> FloatArray:
    out = np.linspace(0.0, 1.0, n_samples)
    out.setflags(write=False)
    return out


@cache
def _sample_basis(degree: int, n_samples: int) -> FloatArray:
    out = bernstein_basis(degree, _sample_params(n_samples))
    out.setflags(write=False)
    return out


def _corridors(ctrl: FloatArray, times: FloatArray, problem: Problem) -> tuple[Worst, Worst]:
    if problem.corridors is None:
        return _none(), _none()
    used = [(s, p) for s, p in enumerate(problem.corridors) if p is not None and p.A.shape[0] > 0]
    if not used:
        return _none(), _none()
    segs = np.fromiter((s for s, _ in used), dtype=np.intp, count=len(used))
    counts = np.fromiter((p.A.shape[0] for _, p in used), dtype=np.intp, count=len(used))
    A = np.concatenate([p.A for _, p in used])  # (R, 3): every plane of every corridor
    b = np.concatenate([p.b for _, p in used])
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    hull_rows, samp_rows = _plane_extremes(ctrl, np.repeat(segs, counts), A)
    # max before subtracting b: fl(x - b) is monotone in x, so this is exact
    hull_seg = np.maximum.reduceat(hull_rows - b, starts)
    samp_seg = np.maximum.reduceat(samp_rows - b, starts)
    hull, samp = _none(), _none()
    i = int(np.argmax(hull_seg))
    if hull_seg[i] > hull.value:
        hull = Worst(float(hull_seg[i]), int(segs[i]))
    i = int(np.argmax(samp_seg))
    if samp_seg[i] > samp.value:
        s = int(segs[i])
        rows = slice(int(starts[i]), int(starts[i] + counts[i]))
        proj = _project(ctrl[np.full(int(counts[i]), s)], A[rows])
        t = int(np.argmax((_sample_basis(DEGREE, SAMPLES_PER_SEGMENT) @ proj.T - b[rows]).max(axis=1)))
        u = _sample_params(SAMPLES_PER_SEGMENT)
        samp = Worst(float(samp_seg[i]), s, time=float(times[s] + u[t] * (times[s + 1] - times[s])))
    return hull, samp


def _plane_extremes(ctrl: FloatArray, row_seg: NDArray[np.intp], A: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Per plane row r, the max of A[r] . x over segment row_seg[r]'s control points and samples.

    a . x(u) is the Bézier curve of the projected control points a . P^j, so
    the samples of every plane come from one Bernstein matmul per block of rows.
    """
    basis = _sample_basis(DEGREE, SAMPLES_PER_SEGMENT)
    n_rows = A.shape[0]
    hull = np.empty(n_rows)
    samp = np.empty(n_rows)
    for a in range(0, n_rows, _ROW_BLOCK):
        z = min(a + _ROW_BLOCK, n_rows)
        proj = _project(ctrl[row_seg[a:z]], A[a:z])  # (rows, 10)
        hull[a:z] = proj.max(axis=1)
        samp[a:z] = (basis @ proj.T).max(axis=0)
    return hull, samp


def _project(pts: FloatArray, A: FloatArray) -> FloatArray:
    """pts (r, 10, 3) against one plane normal per row A (r, 3): (r, 10), fixed summation order."""
    out: FloatArray = pts[:, :, 0] * A[:, None, 0] + pts[:, :, 1] * A[:, None, 1] + pts[:, :, 2] * A[:, None, 2]
    return out
