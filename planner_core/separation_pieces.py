"""Exact pieces of two trajectories on their common intervals, speed bounds and separating planes:
the geometry under the separation certificate (`planner_core.separation_certificate`) and the
planning rows (`planner_core.separation_planning`); `planner_core.separation` tells the method.

- `restrict`, `pieces_on`, `pieces_between`: de Casteljau restrictions of segments to sub-intervals
  (after a trajectory's end, its held last point); `common_knots` / `common_pieces` on the overlap.
- `speed_bound` (continuous-time bound on |velocity|), `peak_speed` (sampled, the receiver's check).
- `cheap_planes` (axis and centroid directions, no solver), `nearest_planes` (Gilbert's steps
  towards the max-margin plane for many pairs at once, with an upper bound on any plane's gap),
  `max_margin_plane` (a small QP), `best_plane` (the cheap one where it clears the need, else the
  max-margin one).

Pure numpy (plus daqp for the small max-margin QPs); no I/O.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from planner_core.bezier import segments_at
from planner_core.problem import FloatArray, Trajectory

IntArray = NDArray[np.intp]

KNOT_TOL = 1e-9  # knots of the two trajectories closer than this (s) are one knot
SPEED_SAMPLES = 64  # per segment, for the receiver's check of the stated speeds


# --- exact restriction of Bézier pieces ----------------------------------------------------


def restrict(ctrl: FloatArray, u0: FloatArray, u1: FloatArray) -> FloatArray:
    """Control points (K, 10, D) of the restriction of each curve ctrl[k] (K, 10, D) to
    [u0[k], u1[k]] within [0, 1]: two de Casteljau splits, vectorised over k (exact up to
    rounding; the curve is the same)."""
    work = np.array(ctrl, dtype=float)
    u0 = np.asarray(u0, dtype=float)
    u1 = np.asarray(u1, dtype=float)
    n = work.shape[1] - 1
    # left part at u1: [0, u1]
    left = np.empty_like(work)
    left[:, 0] = work[:, 0]
    w = work
    t = u1[:, None, None]
    for r in range(1, n + 1):
        w = (1.0 - t) * w[:, :-1] + t * w[:, 1:]
        left[:, r] = w[:, 0]
    # right part of [0, u1] at u0 / u1: [u0, u1]
    v = np.where(u1 > 0.0, u0 / np.where(u1 > 0.0, u1, 1.0), 0.0)[:, None, None]
    right = np.empty_like(work)
    right[:, n] = left[:, n]
    w = left
    for r in range(1, n + 1):
        w = (1.0 - v) * w[:, :-1] + v * w[:, 1:]
        right[:, n - r] = w[:, -1]
    return right


def merge_knots(knots: FloatArray) -> FloatArray:
    k: FloatArray = np.unique(knots)
    if k.size < 2:
        return k
    keep = np.concatenate([[True], np.diff(k) > KNOT_TOL])
    out: FloatArray = k[keep]
    out[-1] = k[-1]  # the span's end stays exact
    return out


def overlap(a: Trajectory, b: Trajectory) -> tuple[float, float]:
    """(from the later start, to the later end): where both are defined (one may be holding)."""
    return max(a.t0, b.t0), max(a.t_end, b.t_end)


def locate(traj: Trajectory, t0: FloatArray, t1: FloatArray) -> tuple[IntArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """Segment, local u0, u1 and "held" (after the end) of each interval [t0, t1] (within one segment)."""
    times = traj.times
    mid = 0.5 * (t0 + t1)
    seg = segments_at(times, mid)
    d = times[seg + 1] - times[seg]
    u0 = np.clip((t0 - times[seg]) / d, 0.0, 1.0)
    u1 = np.clip((t1 - times[seg]) / d, 0.0, 1.0)
    return seg, u0, u1, t0 >= traj.t_end - KNOT_TOL


def pieces_on(traj: Trajectory, knots: FloatArray) -> FloatArray:
    """(K, 10, 3) control points of traj on each [knots[i], knots[i+1]] (knots within traj's span
    or after its end, and including every knot of traj in their range): exact pieces; after the
    end, the held last point."""
    return pieces_between(traj, knots[:-1], knots[1:])


def pieces_between(traj: Trajectory, t0: FloatArray, t1: FloatArray) -> FloatArray:
    seg, u0, u1, held = locate(traj, t0, t1)
    out = restrict(traj.control_points[seg], u0, u1)
    if held.any():
        out[held] = traj.control_points[-1, -1]
    return out


def segment_boxes(traj: Trajectory, t0: FloatArray, t1: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(lo, hi) (K, 3): the box of the whole segment holding each interval (it holds the piece's
    control points: they are convex combinations of the segment's), or the held point."""
    seg, _, _, held = locate(traj, t0, t1)
    ctrl = traj.control_points[seg]
    lo, hi = ctrl.min(axis=1), ctrl.max(axis=1)
    if held.any():
        lo[held] = hi[held] = traj.control_points[-1, -1]
    return lo, hi


def common_knots(a: Trajectory, b: Trajectory, extra: FloatArray | None = None,
                 span: tuple[float, float] | None = None) -> FloatArray:
    """The overlap (cut to `span` when given) split at the union of both knot sets (and `extra`
    times, e.g. a certificate's); a single time when the span leaves nothing."""
    lo, hi = overlap(a, b)
    if span is not None:
        lo, hi = max(lo, span[0]), min(hi, span[1])
        if hi <= lo:
            return np.array([lo])
    parts = [a.times, b.times, np.array([lo, hi])]
    if extra is not None:
        parts.append(np.asarray(extra, dtype=float))
    ks = np.concatenate(parts)
    return merge_knots(ks[(ks >= lo) & (ks <= hi)])


def common_pieces(a: Trajectory, b: Trajectory, extra: FloatArray | None = None,
                  span: tuple[float, float] | None = None) -> tuple[FloatArray, FloatArray, FloatArray]:
    """(knots (K+1,), a's pieces (K, 10, 3), b's pieces (K, 10, 3)) on the overlap (cut to `span`
    when given), split at the union of both knot sets (and `extra` times, e.g. a certificate's)."""
    knots = common_knots(a, b, extra, span)
    if knots.size < 2:
        return knots, np.zeros((0, 10, 3)), np.zeros((0, 10, 3))
    return knots, pieces_on(a, knots), pieces_on(b, knots)


def speed_bound(traj: Trajectory, pieces: int = 3) -> float:
    """An upper bound on |velocity| over the whole trajectory, valid in continuous time: the
    largest norm of the velocity hodograph's control points after `pieces` de Casteljau splits."""
    from planner_core.bezier import hodographs, stacked_pieces

    h = hodographs(traj.control_points, 1, np.diff(traj.times))
    pts = np.matmul(stacked_pieces(h.shape[1] - 1, pieces), h)
    return float(np.sqrt((pts**2).sum(axis=-1)).max())


def peak_speed(traj: Trajectory) -> float:
    from planner_core.bezier import bernstein_basis, hodographs

    h = hodographs(traj.control_points, 1, np.diff(traj.times))
    basis = bernstein_basis(h.shape[1] - 1, np.linspace(0.0, 1.0, SPEED_SAMPLES))
    v = np.matmul(basis, h)
    return float(np.sqrt((v**2).sum(axis=-1)).max())


# --- planes ---------------------------------------------------------------------------------


def direction_gaps(pa: FloatArray, pb: FloatArray, dirs: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """For directions dirs (K, D, 3) over point sets pa (K, p, 3), pb (K, q, 3): the gap
    min n.b - max n.a (K, D), max n.a and min n.b."""
    hi_a = np.einsum("kdx,kpx->kdp", dirs, pa).max(axis=2)
    lo_b = np.einsum("kdx,kpx->kdp", dirs, pb).min(axis=2)
    return lo_b - hi_a, hi_a, lo_b


AXES = np.concatenate([np.eye(3), -np.eye(3)])


def cheap_planes(pa: FloatArray, pb: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Best of the six axis directions and the centroid direction: (normals (K, 3), gap (K,),
    c (K,) the mid-plane). No solver: the broad phase of the certificate."""
    k = pa.shape[0]
    cen = pb.mean(axis=1) - pa.mean(axis=1)
    norm = np.linalg.norm(cen, axis=1, keepdims=True)
    cen = np.where(norm > 0.0, cen / np.where(norm > 0.0, norm, 1.0), np.array([1.0, 0.0, 0.0]))
    dirs = np.concatenate([np.broadcast_to(AXES, (k, 6, 3)), cen[:, None]], axis=1)
    gap, hi_a, lo_b = direction_gaps(pa, pb, dirs)
    best = np.argmax(gap, axis=1)
    r = np.arange(k)
    return dirs[r, best], gap[r, best], 0.5 * (hi_a[r, best] + lo_b[r, best])


GILBERT_STEPS = 24  # Gilbert steps per batch of pairs (each a few array calls over all pairs)
GILBERT_MIN = 4  # fewer pairs than this: one QP each is cheaper than a batch of steps
CONVERGED = 1e-9  # relative: a gap this close to Gilbert's bound is the max-margin one


def nearest_planes(pa: FloatArray, pb: FloatArray, need: FloatArray | None,
                   steps: int = GILBERT_STEPS) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Planes towards the maximum-margin one between point sets pa (K, p, 3) and pb (K, q, 3),
    without a solver, for all K at once: Gilbert's steps towards the point x of the hull of
    {b_i - a_j} nearest the origin (x / |x| is the max-margin normal at the limit). Each step's
    support point is b_argmin - a_argmax along x, so the p q differences are never formed.
    Returns the best plane seen per pair (normals (K, 3), gap = min n.b - max n.a recomputed from
    the points, c the mid-plane), like `cheap_planes`, and `bound` (K,): |x| at the last step, an
    upper bound on the hulls' distance and so on any plane's gap. A gap at or above `need` needs
    no QP; nor does a bound below it (not even the max-margin plane clears `need`). Pairs stop
    once one of the two holds. With `need` None they run to convergence (gap within
    CONVERGED x |x| of the bound: the plane is the max-margin one) or `steps`."""
    k = pa.shape[0]
    r = np.arange(k)
    x = pb.mean(axis=1) - pa.mean(axis=1)
    best_n = np.zeros((k, 3))
    best_n[:, 0] = 1.0
    best_gap = np.full(k, -np.inf)
    best_c = np.zeros(k)
    bound = np.full(k, np.inf)
    live = r
    for _ in range(steps):
        xl = x[live]
        norm = np.sqrt((xl * xl).sum(axis=1))
        bound[live] = norm
        ok = norm > 0.0
        n = xl / np.where(ok, norm, 1.0)[:, None]
        proj_a = np.einsum("kpx,kx->kp", pa[live], n)
        proj_b = np.einsum("kpx,kx->kp", pb[live], n)
        ia, ib = proj_a.argmax(axis=1), proj_b.argmin(axis=1)
        rl = np.arange(live.size)
        hi_a, lo_b = proj_a[rl, ia], proj_b[rl, ib]
        gap = np.where(ok, lo_b - hi_a, -np.inf)
        up = gap > best_gap[live]
        best_n[live[up]], best_gap[live[up]], best_c[live[up]] = n[up], gap[up], 0.5 * (hi_a[up] + lo_b[up])
        # the line search towards the support point s: x + g (s - x), g in [0, 1] minimising |.|
        d = xl - (pb[live, ib] - pa[live, ia])
        dd = (d * d).sum(axis=1)
        g = np.clip((xl * d).sum(axis=1) / np.where(dd > 0.0, dd, 1.0), 0.0, 1.0)
        x[live] = xl - g[:, None] * d
        if need is None:
            go = ok & (dd > 0.0) & (norm - best_gap[live] > CONVERGED * np.maximum(norm, 1.0))
        else:
            go = ok & (best_gap[live] < need[live]) & (norm >= need[live]) & (dd > 0.0)
        live = live[go]
        if live.size == 0:
            break
    return best_n, best_gap, best_c, bound


def max_margin_plane(pa: FloatArray, pb: FloatArray) -> tuple[FloatArray, float, float] | None:
    """The maximum-margin plane between point sets pa (p, 3) and pb (q, 3) (their convex hulls'
    distance): (unit n, gap = min n.b - max n.a, c = mid-plane), or None when the hulls meet
    (the QP is infeasible). The gap is recomputed from the points, so the solver's accuracy
    never enters a certificate."""
    from planner_core.qp import INF, solve_daqp

    centre = 0.5 * (pa.mean(axis=0) + pb.mean(axis=0))
    a, b = pa - centre, pb - centre
    scale = max(float(np.abs(np.concatenate([a, b])).max()), 1e-12)
    a, b = a / scale, b / scale
    # variables (w, beta): min |w|^2 / 2 (+ a tiny weight on beta) s.t. w.a - beta <= -1, w.b - beta >= 1
    G = np.concatenate([np.hstack([a, -np.ones((a.shape[0], 1))]), np.hstack([b, -np.ones((b.shape[0], 1))])])
    lo = np.concatenate([np.full(a.shape[0], -INF), np.ones(b.shape[0])])
    hi = np.concatenate([-np.ones(a.shape[0]), np.full(b.shape[0], INF)])
    P = np.diag([1.0, 1.0, 1.0, 1e-9])
    res = solve_daqp(P, np.zeros(4), G, lo, hi, tol=1e-12)
    if not res.ok or res.x is None:
        return None
    w = res.x[:3]
    nw = float(np.linalg.norm(w))
    if not np.isfinite(nw) or nw == 0.0:
        return None
    n = w / nw
    hi_a = float((pa @ n).max())
    lo_b = float((pb @ n).min())
    return n, lo_b - hi_a, 0.5 * (hi_a + lo_b)


def best_plane(pa: FloatArray, pb: FloatArray, need: float) -> tuple[FloatArray, float, float]:
    """A plane with gap >= need if the cheap directions give one, else the max-margin plane
    (or the best cheap one when the hulls meet)."""
    n, gap, c = cheap_planes(pa[None], pb[None])
    if gap[0] >= need:
        return n[0], float(gap[0]), float(c[0])
    mm = max_margin_plane(pa, pb)
    if mm is not None and mm[1] > gap[0]:
        return mm
    return n[0], float(gap[0]), float(c[0])


@lru_cache(maxsize=1)
def halves_matrix() -> FloatArray:
    """(2, 10, 10) the two halves' maps, built once (read only: shared by every caller)."""
    from planner_core.bezier import subdivision_matrix

    out = np.array(subdivision_matrix(9, 2))
    out.flags.writeable = False
    return out
