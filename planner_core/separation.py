"""Separation between two vehicles' committed trajectories, in continuous time (method.md, "the fleet").

Two trajectories A(t), B(t) (piecewise degree 9, each with its own knots) on one absolute clock.
Their *overlap* runs from the later start to the later end: a trajectory that has ended holds its
last point (that point stays reserved), before its start it is not defined (the caller hands in
trajectories that cover "now"). On the overlap both are split exactly (de Casteljau, a linear map
of each segment's control points) at the union of their knots; on each common interval both are
degree-9 Bézier curves of the same parameter u with control points a_0..a_9 and b_0..b_9. A unit
vector n and a scalar c with

    n . a_k <= c - s'/2   and   n . b_k >= c + s'/2   for every k

keep |A(t) - B(t)| >= s' on the whole interval (convex hull). `s' = s + (v_A + v_B) eps` pays
for a clock offset of at most eps between the vehicles (v: bound speeds). After the overlap both
hold their last points, which are control points of the last interval: its plane certifies the
hold for ever.

- `certify_separation(a, b, s, ...)` -> `SeparationCheck` carrying a `SeparationCertificate` (one
  plane per interval, subdividing an interval where its margin is short) or naming the first
  interval that could not be certified and by how much.
- `verify_separation(a, b, cert)`: what any receiver runs; status-coded, never raises on a bad
  certificate.
- `certify_many(a, others, s, ...)`: the same against many trajectories in one batch;
  `certify_all(traj, neighbours)`: against every neighbour the broad phase finds near.
- Planning against neighbours: `Neighbours` (the other committed trajectories and the rules),
  `neighbour_faces` / `with_neighbours` (per segment of ours, half-spaces n . x <= c on our control
  points: a corridor face, so every planner path takes them and the QP stays a QP),
  `planning_rows` (time-resolved rows per common piece, for the general jet solver:
  `jets.ProblemCache(extra_rows=...)`), `separation_rows` (the rows of an existing certificate's
  intervals on our control points). `planning.plan(..., neighbours=)` and
  `replan.ReplanOptions(neighbours=)` use them (docs/separation.md).
- Broad phase: `near_pairs` (space-time boxes, a sorted sweep): far neighbours cost nothing.

Pure numpy (plus daqp for the small max-margin QPs); no I/O.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planner_core.broadphase import overlapping_pairs
from planner_core.problem import Bounds, FloatArray, Polytope, Problem, Trajectory

IntArray = NDArray[np.intp]

KNOT_TOL = 1e-9  # knots of the two trajectories closer than this (s) are one knot
FAR = 1e30  # "for ever" in a time box (a held last point)
MAX_DEPTH = 4  # an interval whose margin is short is halved up to this many times (16 pieces)
SPEED_SAMPLES = 64  # per segment, for the receiver's check of the stated speeds

__all__ = [
    "Neighbours",
    "SeparationCertificate",
    "SeparationCheck",
    "SeparationRows",
    "SeparationStatus",
    "bound_speed",
    "certify_many",
    "certify_separation",
    "common_pieces",
    "near_pairs",
    "neighbour_faces",
    "planning_rows",
    "separation_rows",
    "speed_bound",
    "verify_separation",
    "with_neighbours",
]


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


def _merge_knots(knots: FloatArray) -> FloatArray:
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


def _locate(traj: Trajectory, t0: FloatArray, t1: FloatArray) -> tuple[IntArray, FloatArray, FloatArray, NDArray[np.bool_]]:
    """Segment, local u0, u1 and "held" (after the end) of each interval [t0, t1] (within one segment)."""
    times = traj.times
    mid = 0.5 * (t0 + t1)
    seg = np.clip(np.searchsorted(times, mid, side="right") - 1, 0, traj.n_segments - 1)
    d = times[seg + 1] - times[seg]
    u0 = np.clip((t0 - times[seg]) / d, 0.0, 1.0)
    u1 = np.clip((t1 - times[seg]) / d, 0.0, 1.0)
    return seg, u0, u1, t0 >= traj.t_end - KNOT_TOL


def pieces_on(traj: Trajectory, knots: FloatArray) -> FloatArray:
    """(K, 10, 3) control points of traj on each [knots[i], knots[i+1]] (knots within traj's span
    or after its end, and including every knot of traj in their range): exact pieces; after the
    end, the held last point."""
    return _pieces(traj, knots[:-1], knots[1:])


def _pieces(traj: Trajectory, t0: FloatArray, t1: FloatArray) -> FloatArray:
    seg, u0, u1, held = _locate(traj, t0, t1)
    out = restrict(traj.control_points[seg], u0, u1)
    if held.any():
        out[held] = traj.control_points[-1, -1]
    return out


def _boxes(traj: Trajectory, t0: FloatArray, t1: FloatArray) -> tuple[FloatArray, FloatArray]:
    """(lo, hi) (K, 3): the box of the whole segment holding each interval (it holds the piece's
    control points: they are convex combinations of the segment's), or the held point."""
    seg, _, _, held = _locate(traj, t0, t1)
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
    return _merge_knots(ks[(ks >= lo) & (ks <= hi)])


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


def _peak_speed(traj: Trajectory) -> float:
    from planner_core.bezier import bernstein_basis, hodographs

    h = hodographs(traj.control_points, 1, np.diff(traj.times))
    basis = bernstein_basis(h.shape[1] - 1, np.linspace(0.0, 1.0, SPEED_SAMPLES))
    v = np.matmul(basis, h)
    return float(np.sqrt((v**2).sum(axis=-1)).max())


# --- planes ---------------------------------------------------------------------------------


def _gaps(pa: FloatArray, pb: FloatArray, dirs: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """For directions dirs (K, D, 3) over point sets pa (K, p, 3), pb (K, q, 3): the gap
    min n.b - max n.a (K, D), max n.a and min n.b."""
    hi_a = np.einsum("kdx,kpx->kdp", dirs, pa).max(axis=2)
    lo_b = np.einsum("kdx,kpx->kdp", dirs, pb).min(axis=2)
    return lo_b - hi_a, hi_a, lo_b


_AXES = np.concatenate([np.eye(3), -np.eye(3)])


def _cheap_planes(pa: FloatArray, pb: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Best of the six axis directions and the centroid direction: (normals (K, 3), gap (K,),
    c (K,) the mid-plane). No solver: the broad phase of the certificate."""
    k = pa.shape[0]
    cen = pb.mean(axis=1) - pa.mean(axis=1)
    norm = np.linalg.norm(cen, axis=1, keepdims=True)
    cen = np.where(norm > 0.0, cen / np.where(norm > 0.0, norm, 1.0), np.array([1.0, 0.0, 0.0]))
    dirs = np.concatenate([np.broadcast_to(_AXES, (k, 6, 3)), cen[:, None]], axis=1)
    gap, hi_a, lo_b = _gaps(pa, pb, dirs)
    best = np.argmax(gap, axis=1)
    r = np.arange(k)
    return dirs[r, best], gap[r, best], 0.5 * (hi_a[r, best] + lo_b[r, best])


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


def _plane(pa: FloatArray, pb: FloatArray, need: float) -> tuple[FloatArray, float, float]:
    """A plane with gap >= need if the cheap directions give one, else the max-margin plane
    (or the best cheap one when the hulls meet)."""
    n, gap, c = _cheap_planes(pa[None], pb[None])
    if gap[0] >= need:
        return n[0], float(gap[0]), float(c[0])
    mm = max_margin_plane(pa, pb)
    if mm is not None and mm[1] > gap[0]:
        return mm
    return n[0], float(gap[0]), float(c[0])


# --- the certificate -------------------------------------------------------------------------


class SeparationStatus(enum.Enum):
    OK = "ok"
    TOO_CLOSE = "too close"  # an interval whose pieces cannot be (or are not) separated by s'
    NOT_COVERED = "not covered"  # the certificate does not span the overlap
    SPEED = "speed understated"  # a stated bound speed is below the trajectory's own speed
    MALFORMED = "malformed"  # shapes, times or numbers that are not a certificate


@dataclass(frozen=True)
class SeparationCertificate:
    """One plane per interval [times[i], times[i+1]]: n_i . A <= c_i - s'/2, n_i . B >= c_i + s'/2
    with s' = separation + (speed_a + speed_b) clock_tolerance (`required`). A is the
    trajectory certified first (`certify_separation(a, b, ...)`). The last plane also covers
    both held end points after times[-1]."""

    times: FloatArray  # (K+1,) increasing, absolute
    normals: FloatArray  # (K, 3) unit
    offsets: FloatArray  # (K,) c
    separation: float  # s, centre to centre (m)
    clock_tolerance: float = 0.0  # eps (s)
    speed_a: float = 0.0  # bound speeds (m/s) that pay for eps
    speed_b: float = 0.0

    @property
    def required(self) -> float:
        """s' = s + (v_A + v_B) eps."""
        return float(self.separation + (self.speed_a + self.speed_b) * self.clock_tolerance)

    @property
    def n_intervals(self) -> int:
        return int(self.offsets.shape[0])

    def to_dict(self) -> dict[str, Any]:
        return {"times": self.times.tolist(), "normals": self.normals.tolist(), "offsets": self.offsets.tolist(),
                "separation": self.separation, "clock_tolerance": self.clock_tolerance,
                "speed_a": self.speed_a, "speed_b": self.speed_b}

    @staticmethod
    def from_dict(d: dict[str, Any]) -> SeparationCertificate:
        """Shapes are checked by `verify_separation` (a malformed certificate is a status there)."""
        return SeparationCertificate(np.asarray(d["times"], dtype=float), np.asarray(d["normals"], dtype=float),
                                     np.asarray(d["offsets"], dtype=float), float(d["separation"]),
                                     float(d.get("clock_tolerance", 0.0)), float(d.get("speed_a", 0.0)),
                                     float(d.get("speed_b", 0.0)))


@dataclass(frozen=True)
class SeparationCheck:
    """The outcome of certifying or verifying. When not OK, `interval` is the first failing
    interval (of the certificate when verifying, of the common pieces when certifying), `span` its
    times and `shortfall` by how much (m) the separation falls short there."""

    status: SeparationStatus
    certificate: SeparationCertificate | None = None
    interval: int | None = None
    span: tuple[float, float] | None = None
    shortfall: float = 0.0
    min_gap: float = np.inf  # the smallest certified gap n.b - n.a over all intervals (a distance bound)
    message: str = ""
    stats: dict[str, Any] = field(default_factory=dict, compare=False)

    @property
    def ok(self) -> bool:
        return self.status is SeparationStatus.OK


def certify_separation(
    a: Trajectory,
    b: Trajectory,
    separation: float,
    *,
    clock_tolerance: float = 0.0,
    speeds: tuple[float, float] | None = None,
    max_depth: int = MAX_DEPTH,
    exact: bool = False,
    span: tuple[float, float] | None = None,
) -> SeparationCheck:
    """A certificate that A and B keep `separation` (+ the clock's price) at every instant of the
    overlap and after it, or the first common interval that could not be certified.

    `speeds` (v_A, v_B): bound speeds that pay for `clock_tolerance`; default each trajectory's
    own continuous-time speed bound (`speed_bound`). An interval whose best plane is short of
    s' is halved (both pieces at the same u, exactly) up to `max_depth` times. `exact`: the
    maximum-margin plane on every interval (default: an axis plane between the two segments'
    boxes, or an axis or centroid plane between the pieces, where that already clears s'; the
    max-margin QP only where none does). `span` (t0, t1): certify only that part of the overlap
    (a local replan's rebuilt part); the certificate then covers only it, and its last plane
    covers no hold unless the span reaches the overlap's end."""
    return certify_many(a, (b,), separation, clock_tolerance=clock_tolerance,
                        speeds=None if speeds is None else (speeds,), max_depth=max_depth, exact=exact, span=span)[0]


def certify_many(
    a: Trajectory,
    others: Sequence[Trajectory],
    separation: float,
    *,
    clock_tolerance: float = 0.0,
    speeds: Sequence[tuple[float, float]] | None = None,
    max_depth: int = MAX_DEPTH,
    exact: bool = False,
    span: tuple[float, float] | None = None,
) -> list[SeparationCheck]:
    """`certify_separation` of A against each of `others`, batched: the intervals of every pair
    are located, boxed and split in a few array operations (one de Casteljau pass for all)."""
    if not separation >= 0.0 or not clock_tolerance >= 0.0:
        raise ValueError(f"separation and clock_tolerance must be >= 0, got {separation}, {clock_tolerance}")
    nk = len(others)
    if speeds is None:
        sa = speed_bound(a) if clock_tolerance > 0.0 else 0.0
        sp = [(sa, speed_bound(b) if clock_tolerance > 0.0 else 0.0) for b in others]
    else:
        sp = [(float(x), float(y)) for x, y in speeds]
    needs = [separation + (va + vb) * clock_tolerance for va, vb in sp]
    knots = [common_knots(a, b, span=span) for b in others]
    counts = np.array([max(k.size - 1, 0) for k in knots], dtype=np.intp)
    starts = np.concatenate([[0], np.cumsum(counts)])
    k0 = np.concatenate([k[:-1] for k in knots]) if nk else np.zeros(0)
    k1 = np.concatenate([k[1:] for k in knots]) if nk else np.zeros(0)
    need = np.repeat(np.asarray(needs, dtype=float), counts)
    # boxes of the whole segments first (no splitting)
    alo, ahi = _boxes(a, k0, k1)
    blo, bhi = np.empty_like(alo), np.empty_like(ahi)
    b_seg = np.zeros(k0.size, dtype=np.intp)
    b_u0, b_u1 = np.zeros(k0.size), np.zeros(k0.size)
    b_held = np.zeros(k0.size, dtype=bool)
    for j, b in enumerate(others):
        sl = slice(int(starts[j]), int(starts[j + 1]))
        b_seg[sl], b_u0[sl], b_u1[sl], b_held[sl] = _locate(b, k0[sl], k1[sl])
        ctrl = b.control_points[b_seg[sl]]
        blo[sl], bhi[sl] = ctrl.min(axis=1), ctrl.max(axis=1)
        if b_held[sl].any():
            h = np.flatnonzero(b_held[sl]) + sl.start
            blo[h] = bhi[h] = b.control_points[-1, -1]
    gaps = np.concatenate([blo - ahi, alo - bhi], axis=1)
    mids = np.concatenate([0.5 * (ahi + blo), -0.5 * (alo + bhi)], axis=1)
    best = np.argmax(gaps, axis=1)
    r = np.arange(k0.size)
    cheap_n, cheap_gap, cheap_c = _AXES[best], gaps[r, best], mids[r, best]
    todo = r if exact else np.flatnonzero(cheap_gap < need)
    pa = np.zeros((k0.size, 10, 3))
    pb = np.zeros((k0.size, 10, 3))
    if todo.size:
        pa[todo] = _pieces(a, k0[todo], k1[todo])
        owner = np.repeat(np.arange(nk), counts)
        ctrl_b = np.stack([others[int(o)].control_points[int(sg)] for o, sg in zip(owner[todo], b_seg[todo], strict=True)])
        pb[todo] = restrict(ctrl_b, b_u0[todo], b_u1[todo])
        for i in todo[b_held[todo]].tolist():
            pb[i] = others[int(owner[i])].control_points[-1, -1]
        cn, cg, cc = _cheap_planes(pa[todo], pb[todo])
        better = cg > cheap_gap[todo]
        cheap_n[todo[better]], cheap_gap[todo[better]], cheap_c[todo[better]] = cn[better], cg[better], cc[better]
    return [_assemble_certificate(knots[j], int(starts[j]), cheap_n, cheap_gap, cheap_c, pa, pb, needs[j],
                                  separation, clock_tolerance, sp[j], max_depth, exact) for j in range(nk)]


def _halves() -> FloatArray:
    from planner_core.bezier import subdivision_matrix

    return subdivision_matrix(9, 2)


def _assemble_certificate(knots: FloatArray, first: int, cheap_n: FloatArray, cheap_gap: FloatArray,
                          cheap_c: FloatArray, pa: FloatArray, pb: FloatArray, need: float, separation: float,
                          clock_tolerance: float, speeds: tuple[float, float], max_depth: int,
                          exact: bool) -> SeparationCheck:
    """One pair's intervals (rows first.. of the batch) -> its certificate or first failure."""
    if knots.size < 2:
        return SeparationCheck(SeparationStatus.OK, None, message="no overlap within the span")
    halves = _halves()
    n_qp = 0
    out_t: list[float] = []
    out_n: list[FloatArray] = []
    out_c: list[float] = []
    min_gap = np.inf
    for i in range(knots.size - 1):
        g = first + i
        if not exact and cheap_gap[g] >= need:
            out_t.append(float(knots[i]))
            out_n.append(cheap_n[g])
            out_c.append(float(cheap_c[g]))
            min_gap = min(min_gap, float(cheap_gap[g]))
            continue
        # a stack of (t0, t1, a-piece, b-piece, depth), worked depth first so the output stays in time order
        stack: list[tuple[float, float, FloatArray, FloatArray, int]] = [(float(knots[i]), float(knots[i + 1]), pa[g], pb[g], 0)]
        while stack:
            t0, t1, qa, qb, depth = stack.pop()
            n_qp += 1
            if exact:
                mm = max_margin_plane(qa, qb)
                n, gap, c = mm if mm is not None else _plane(qa, qb, np.inf)
            else:
                n, gap, c = _plane(qa, qb, need)
            if gap >= need:
                out_t.append(t0)
                out_n.append(n)
                out_c.append(c)
                min_gap = min(min_gap, gap)
                continue
            if depth >= max_depth:
                msg = (f"interval {i} [{knots[i]:.6g}, {knots[i + 1]:.6g}] s: the pieces come within "
                       f"{max(gap, 0.0):.4g} m (hull gap) of each other on [{t0:.6g}, {t1:.6g}] s, "
                       f"{need - gap:.4g} m short of {need:.4g} m")
                return SeparationCheck(SeparationStatus.TOO_CLOSE, None, i, (float(knots[i]), float(knots[i + 1])),
                                       float(need - gap), min_gap, msg, {"qps": n_qp})
            tm = 0.5 * (t0 + t1)
            stack.append((tm, t1, halves[1] @ qa, halves[1] @ qb, depth + 1))
            stack.append((t0, tm, halves[0] @ qa, halves[0] @ qb, depth + 1))
    out_t.append(float(knots[-1]))
    cert = SeparationCertificate(np.array(out_t), np.array(out_n).reshape(-1, 3), np.array(out_c), float(separation),
                                 float(clock_tolerance), float(speeds[0]), float(speeds[1]))
    return SeparationCheck(SeparationStatus.OK, cert, min_gap=float(min_gap),
                           message=f"separated by >= {min_gap:.4g} m (required {need:.4g} m) on {cert.n_intervals} intervals",
                           stats={"qps": n_qp, "common_intervals": int(knots.size - 1)})


def verify_separation(a: Trajectory, b: Trajectory, cert: SeparationCertificate, *, tol: float = 1e-9,
                      check_speeds: bool = True) -> SeparationCheck:
    """What a receiver runs: does `cert` prove that A (`a`) and B keep s' at every instant?

    Both trajectories are split at the union of their knots and the certificate's times (at
    least the certifier's splits); every piece must lie on its side of its interval's plane with
    s'/2 to spare (tolerance `tol`, m). The certificate must span the overlap; with a clock
    tolerance, the stated speeds must not be below the trajectories' sampled peak speeds
    (`check_speeds`)."""
    times, normals, offsets = (np.asarray(x, dtype=float) for x in (cert.times, cert.normals, cert.offsets))
    k = offsets.shape[0] if offsets.ndim == 1 else -1
    if (k < 1 or times.shape != (k + 1,) or normals.shape != (k, 3) or not np.all(np.isfinite(times))
            or not np.all(np.isfinite(normals)) or not np.all(np.isfinite(offsets)) or not np.all(np.diff(times) > 0.0)
            or not np.all(np.linalg.norm(normals, axis=1) > 0.0) or not cert.required >= 0.0):
        return SeparationCheck(SeparationStatus.MALFORMED, cert, message="the certificate's arrays are not "
                               "K+1 increasing finite times, K non-zero normals and K offsets")
    lo, hi = overlap(a, b)
    if times[0] > lo + KNOT_TOL or times[-1] < hi - KNOT_TOL:
        return SeparationCheck(SeparationStatus.NOT_COVERED, cert, message=f"the certificate spans [{times[0]:.6g}, "
                               f"{times[-1]:.6g}] s, the overlap is [{lo:.6g}, {hi:.6g}] s")
    if check_speeds and cert.clock_tolerance > 0.0:
        for name, traj, v in (("A", a, cert.speed_a), ("B", b, cert.speed_b)):
            peak = _peak_speed(traj)
            if v < peak - 1e-9:
                return SeparationCheck(SeparationStatus.SPEED, cert, shortfall=float((peak - v) * cert.clock_tolerance),
                                       message=f"the bound speed stated for {name} ({v:.4g} m/s) is below its "
                                       f"trajectory's peak speed ({peak:.4g} m/s)")
    knots, pa, pb = common_pieces(a, b, extra=times[(times > lo) & (times < hi)])
    mid = 0.5 * (knots[:-1] + knots[1:])
    which = np.clip(np.searchsorted(times, mid, side="right") - 1, 0, k - 1)
    scale = np.linalg.norm(normals, axis=1)
    n = normals[which] / scale[which, None]
    c = offsets[which] / scale[which]
    half = 0.5 * cert.required
    slack_a = (c - half) - np.einsum("kx,kpx->kp", n, pa).max(axis=1)
    slack_b = np.einsum("kx,kpx->kp", n, pb).min(axis=1) - (c + half)
    slack = np.minimum(slack_a, slack_b)
    gap = np.einsum("kx,kpx->kp", n, pb).min(axis=1) - np.einsum("kx,kpx->kp", n, pa).max(axis=1)
    bad = np.flatnonzero(slack < -tol)
    if bad.size:
        p = int(bad[0])
        i = int(which[p])
        side = "A" if slack_a[p] < slack_b[p] else "B"
        msg = (f"interval {i} [{times[i]:.6g}, {times[i + 1]:.6g}] s: {side} crosses its side of the plane by "
               f"{-slack[p]:.4g} m on [{knots[p]:.6g}, {knots[p + 1]:.6g}] s (required {cert.required:.4g} m)")
        return SeparationCheck(SeparationStatus.TOO_CLOSE, cert, i, (float(times[i]), float(times[i + 1])),
                               float(-slack[p]), float(gap.min()), msg)
    return SeparationCheck(SeparationStatus.OK, cert, min_gap=float(gap.min()),
                           message=f"verified: >= {float(gap.min()):.4g} m apart (required {cert.required:.4g} m)")


# --- broad phase ----------------------------------------------------------------------------


def space_time_boxes(traj: Trajectory) -> tuple[FloatArray, FloatArray]:
    """(lo, hi) (S+1, 4) boxes in (t, x, y, z): one per segment (its control points' box over its
    time span) and one for the held last point, from t_end for ever."""
    ctrl = traj.control_points
    lo = np.empty((traj.n_segments + 1, 4))
    hi = np.empty_like(lo)
    lo[:-1, 0], hi[:-1, 0] = traj.times[:-1], traj.times[1:]
    lo[:-1, 1:], hi[:-1, 1:] = ctrl.min(axis=1), ctrl.max(axis=1)
    lo[-1, 0], hi[-1, 0] = traj.t_end, FAR
    lo[-1, 1:] = hi[-1, 1:] = ctrl[-1, -1]
    return lo, hi


def near_pairs(qlo: FloatArray, qhi: FloatArray, olo: FloatArray, ohi: FloatArray, distance: float) -> tuple[IntArray, IntArray]:
    """(query i, box k) pairs of space-time boxes (.., 4) that overlap in time and come within
    `distance` in space (each axis; boxes grown by distance/2 each): a sorted sweep
    (`planner_core.broadphase`), so far boxes are never looked at one by one."""
    grow = np.array([KNOT_TOL, 0.5 * distance + 1e-9, 0.5 * distance + 1e-9, 0.5 * distance + 1e-9])
    return overlapping_pairs(qlo - grow, qhi + grow, olo - grow, ohi + grow)


# --- planning against neighbours ---------------------------------------------------------------


@dataclass(frozen=True)
class Neighbours:
    """Other vehicles' committed trajectories and the rule to keep from them.

    `separation` s (m, centre to centre), `clock_tolerance` eps (s), `speed` our bound speed
    (default: the problem's velocity bounds, `bound_speed`) and `speeds` theirs (default: each
    trajectory's own continuous-time speed bound) for s' = s + (v + v_k) eps.
    `reference`: our previous plan (its planes are kept); default the straight segments between
    the problem's waypoints at its times. `reach` (m): how far our new plan may stray from the
    reference; neighbours farther than s' + reach from a segment get no face (the certification
    after planning still checks every neighbour, so nothing unsafe is accepted)."""

    trajectories: tuple[Trajectory, ...]
    separation: float
    clock_tolerance: float = 0.0
    speed: float | None = None
    speeds: tuple[float, ...] | None = None
    reference: Trajectory | None = None
    reach: float = 5.0

    def __post_init__(self) -> None:
        if not self.separation >= 0.0 or not self.clock_tolerance >= 0.0 or not self.reach >= 0.0:
            raise ValueError("separation, clock_tolerance and reach must be >= 0")
        if self.speeds is not None and len(self.speeds) != len(self.trajectories):
            raise ValueError(f"speeds: one per neighbour ({len(self.trajectories)}), got {len(self.speeds)}")
        object.__setattr__(self, "trajectories", tuple(self.trajectories))

    def speed_of(self, k: int) -> float:
        if self.clock_tolerance == 0.0:
            return 0.0
        return float(self.speeds[k]) if self.speeds is not None else speed_bound(self.trajectories[k])

    @property
    def our_speed(self) -> float:
        if self.clock_tolerance == 0.0:
            return 0.0
        if self.speed is None or not np.isfinite(self.speed):
            raise ValueError("speed: a clock tolerance needs our finite bound speed (or finite velocity bounds)")
        return float(self.speed)

    def for_bounds(self, bounds: Bounds) -> Neighbours:
        """These neighbours with our bound speed taken from `bounds` when not given."""
        from dataclasses import replace

        if self.speed is not None or self.clock_tolerance == 0.0:
            return self
        out = replace(self, speed=bound_speed(bounds))
        if "boxes" in self.__dict__:  # the same trajectories: their boxes carry over
            out.__dict__["boxes"] = self.__dict__["boxes"]
        return out

    def required(self, k: int) -> float:
        """s' against neighbour k."""
        return float(self.separation + (self.our_speed + self.speed_of(k)) * self.clock_tolerance)

    @cached_property
    def boxes(self) -> tuple[FloatArray, FloatArray, IntArray]:
        """Every neighbour's space-time boxes stacked: (lo, hi, owner)."""
        if not self.trajectories:
            return np.zeros((0, 4)), np.zeros((0, 4)), np.zeros(0, dtype=np.intp)
        parts = [space_time_boxes(t) for t in self.trajectories]
        owner = np.concatenate([np.full(p[0].shape[0], k, dtype=np.intp) for k, p in enumerate(parts)])
        return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts]), owner

    @cached_property
    def max_required(self) -> float:
        return max((self.required(k) for k in range(len(self.trajectories))), default=self.separation)


def bound_speed(bounds: Bounds) -> float:
    """The largest speed any plan within `bounds` can have (velocity box, with the horizontal norm
    bound when it is tighter): a bound speed for the clock's price."""
    lo, hi = bounds.axis_limits()
    v = np.maximum(np.abs(lo[0]), np.abs(hi[0]))
    horizontal = min(float(np.hypot(v[0], v[1])), float(bounds.horizontal[0]))
    return float(np.hypot(horizontal, v[2]))


def straight_reference(problem: Problem) -> FloatArray:
    """(m-1, 10, 3) control points of the straight segments between the waypoints."""
    w = problem.waypoints
    u = np.linspace(0.0, 1.0, 10)[None, :, None]
    return np.asarray(w[:-1, None, :] * (1.0 - u) + w[1:, None, :] * u)


def reference_points(times: FloatArray, straight: FloatArray, ref: Trajectory | None,
                     segments: Sequence[int]) -> list[FloatArray]:
    """Our reference points (p, 3) on each listed segment of `times`: the control points of the
    previous plan's pieces over the segment's span where it covers it, else the straight
    segment's. They only choose each face's direction."""
    out = [straight[s] for s in segments]
    if ref is None:
        return out
    for r, s in enumerate(segments):
        t0, t1 = float(times[s]), float(times[s + 1])
        if t0 >= ref.t0 - KNOT_TOL and t1 <= ref.t_end + KNOT_TOL:
            ks = ref.times[(ref.times > t0) & (ref.times < t1)]
            out[r] = pieces_on(ref, _merge_knots(np.concatenate([[t0, t1], ks]))).reshape(-1, 3)
    return out


class NoFace(Exception):
    """One face per segment cannot hold our reference away from a neighbour (it sweeps across our
    segment's path during its span): time-resolved rows are needed (`planning_rows`)."""


def neighbour_faces(times: FloatArray, reference: Sequence[FloatArray], neighbours: Neighbours,
                    segments: Sequence[int], give_up: bool = False) -> dict[int, tuple[FloatArray, FloatArray]]:
    """Per listed segment s of ours (span [times[s], times[s+1]], reference points reference[r]
    for the r-th listed segment):
    half-spaces (A (f, 3), b (f,)) with A x <= b on our control points, one per near neighbour:
    n . x <= min_k n . b_k - s', n the max-margin direction between our reference and the
    neighbour's pieces over the segment's span. Every point of ours on that side is s' from
    every point of the neighbour's hull on the span: with our control points inside, the segment
    keeps s' from the neighbour at every instant of it. Segments with no near neighbour are
    absent. Linear in our control points: the QP stays a QP."""
    segs = list(segments)
    if not segs or not neighbours.trajectories:
        return {}
    olo, ohi, owner = neighbours.boxes
    qlo = np.empty((len(segs), 4))
    qhi = np.empty_like(qlo)
    sa = np.asarray(segs, dtype=np.intp)
    qlo[:, 0], qhi[:, 0] = times[sa], times[sa + 1]
    qlo[:, 1:] = np.array([r.min(axis=0) for r in reference])
    qhi[:, 1:] = np.array([r.max(axis=0) for r in reference])
    qi, bk = near_pairs(qlo, qhi, olo, ohi, neighbours.max_required + neighbours.reach)
    # one row per (pair, piece of the neighbour over our segment's span): located here, split below
    # in one de Casteljau pass for every pair
    pairs: list[tuple[int, int]] = []
    piece_pair: list[int] = []
    t_lo: list[FloatArray] = []
    t_hi: list[FloatArray] = []
    for q, k in sorted(set(zip(qi.tolist(), owner[bk].tolist(), strict=True))):
        s = segs[q]
        nb = neighbours.trajectories[k]
        t0, t1 = float(times[s]), float(times[s + 1])
        lo_t = max(t0, nb.t0)
        if lo_t >= t1:
            continue
        ks = nb.times[(nb.times > lo_t) & (nb.times < t1)]
        knots = _merge_knots(np.concatenate([[lo_t, t1], ks, [nb.t_end] if lo_t < nb.t_end < t1 else []]))
        piece_pair.extend([len(pairs)] * (knots.size - 1))
        pairs.append((q, k))
        t_lo.append(knots[:-1])
        t_hi.append(knots[1:])
    if not pairs:
        return {}
    pp = np.asarray(piece_pair, dtype=np.intp)
    k0, k1 = np.concatenate(t_lo), np.concatenate(t_hi)
    pair_owner = np.array([k for _, k in pairs], dtype=np.intp)
    ctrl = np.empty((k0.size, 10, 3))
    u0, u1 = np.empty(k0.size), np.empty(k0.size)
    held = np.zeros(k0.size, dtype=bool)
    piece_owner = pair_owner[pp]
    for k in np.unique(pair_owner).tolist():
        rows = np.flatnonzero(piece_owner == k)
        nb = neighbours.trajectories[k]
        sg, u0[rows], u1[rows], held[rows] = _locate(nb, k0[rows], k1[rows])
        ctrl[rows] = nb.control_points[sg]
        ctrl[rows[held[rows]]] = nb.control_points[-1, -1]
    pieces = restrict(ctrl, u0, u1)
    # cheap planes for every pair at once (pad each pair's points by repeating its first piece)
    count = np.bincount(pp, minlength=len(pairs))
    width = int(count.max())
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    slot = np.arange(k0.size) - first[pp]
    padded = np.repeat(pieces[first][:, None], width, axis=1)  # (pairs, width, 10, 3)
    padded[pp, slot] = pieces
    pts_all = padded.reshape(len(pairs), width * 10, 3)
    n_ref = max(r.shape[0] for r in reference)
    refs = np.stack([reference[q][np.minimum(np.arange(n_ref), reference[q].shape[0] - 1)] for q, _ in pairs])
    cn, cg, _ = _cheap_planes(refs, pts_all)
    faces: dict[int, tuple[list[FloatArray], list[float]]] = {}
    for j, (q, k) in enumerate(pairs):
        need = neighbours.required(k)
        pts = pts_all[j]
        if cg[j] >= need + neighbours.reach:
            n = cn[j]  # room for `reach` already: no solver
        else:
            n, gap, _ = _plane(reference[q], pieces[pp == j].reshape(-1, 3), np.inf)
            if give_up and gap < need:
                raise NoFace(f"neighbour {k} comes within {max(gap, 0.0):.4g} m of our reference over segment "
                             f"{segs[q]} [{times[segs[q]]:.6g}, {times[segs[q] + 1]:.6g}] s (one plane for the "
                             f"segment; {need:.4g} m required)")
        rhs = float((pts @ n).min()) - need
        entry = faces.setdefault(segs[q], ([], []))
        entry[0].append(n)
        entry[1].append(rhs)
    return {s: (np.array(a), np.array(b)) for s, (a, b) in faces.items()}


def add_faces(corridor: Polytope | None, face: tuple[FloatArray, FloatArray] | None) -> Polytope | None:
    if face is None:
        return corridor
    if corridor is None:
        return Polytope(face[0], face[1])
    return Polytope(np.vstack([corridor.A, face[0]]), np.concatenate([corridor.b, face[1]]))


def with_neighbours(problem: Problem, neighbours: Neighbours) -> tuple[Problem, str | None]:
    """The problem with each segment's corridor cut by its neighbour faces, and a reason when a
    waypoint (fixed by the problem) already lies on the wrong side of a face."""
    from dataclasses import replace

    neighbours = neighbours.for_bounds(problem.bounds)
    segs = list(range(problem.m - 1))
    ref = reference_points(problem.times, straight_reference(problem), neighbours.reference, segs)
    try:
        faces = neighbour_faces(problem.times, ref, neighbours, segs, give_up=True)
    except NoFace as exc:
        return problem, str(exc)
    if not faces:
        return problem, None
    base = problem.corridors if problem.corridors is not None else (None,) * (problem.m - 1)
    cors = tuple(add_faces(c, faces.get(s)) for s, c in enumerate(base))
    why = None
    for s, (A, b) in sorted(faces.items()):
        over = (problem.waypoints[s : s + 2] @ A.T - b).max()
        if over > 1e-9:
            why = (f"a waypoint of segment {s} [{problem.times[s]:.6g}, {problem.times[s + 1]:.6g}] s is within the "
                   f"separation of a neighbour's trajectory over that span (by {over:.4g} m)")
            break
    return replace(problem, corridors=cors), why


def certify_all(traj: Trajectory, neighbours: Neighbours, t_from: float | None = None,
                t_to: float | None = None) -> tuple[list[tuple[int, SeparationCertificate]], SeparationCheck | None, int]:
    """Certificates of `traj` against every neighbour near it (the space-time broad phase proves the
    others: their boxes stay s' apart on every axis); the first failure, if any; and how many
    neighbours needed a certificate. `t_from`/`t_to` restrict the check to our segments touching
    that span (a local replan's rebuilt part)."""
    if not neighbours.trajectories:
        return [], None, 0
    qlo, qhi = space_time_boxes(traj)
    span = None
    if t_from is not None or t_to is not None:
        span = (t_from if t_from is not None else -FAR, t_to if t_to is not None else FAR)
        keep = (qhi[:, 0] >= span[0]) & (qlo[:, 0] <= span[1])
        qlo, qhi = qlo[keep], qhi[keep]
    olo, ohi, owner = neighbours.boxes
    _, bk = near_pairs(qlo, qhi, olo, ohi, neighbours.max_required)
    near = sorted(set(owner[bk].tolist()))
    certs: list[tuple[int, SeparationCertificate]] = []
    checks = certify_many(traj, [neighbours.trajectories[k] for k in near], neighbours.separation,
                          clock_tolerance=neighbours.clock_tolerance,
                          speeds=[(neighbours.our_speed, neighbours.speed_of(k)) for k in near], span=span)
    for k, chk in zip(near, checks, strict=True):
        if not chk.ok:
            return certs, replace_message(chk, f"neighbour {k}: {chk.message}"), len(near)
        if chk.certificate is not None:
            certs.append((k, chk.certificate))
    return certs, None, len(near)


def replace_message(chk: SeparationCheck, message: str) -> SeparationCheck:
    from dataclasses import replace

    return replace(chk, message=message)


# --- rows of a certificate on our control points ---------------------------------------------


@dataclass(frozen=True)
class SeparationRows:
    """Row r: sum_i weights[r, i] (normal[r] . P[segment[r], i]) <= rhs[r] on our control points P
    (m-1, 10, 3): the control point of one split piece (a fixed combination of its segment's
    control points) on our side of a certificate's plane."""

    segment: IntArray  # (R,)
    weights: FloatArray  # (R, 10)
    normal: FloatArray  # (R, 3)
    rhs: FloatArray  # (R,)

    def values(self, ctrl: FloatArray) -> FloatArray:
        """(R,) left-hand sides for control points ctrl (m-1, 10, 3)."""
        proj = np.einsum("rx,rix->ri", self.normal, ctrl[self.segment])
        out: FloatArray = np.einsum("ri,ri->r", self.weights, proj)
        return out

    def violation(self, ctrl: FloatArray) -> float:
        if self.rhs.size == 0:
            return -np.inf
        return float((self.values(ctrl) - self.rhs).max())


def separation_rows(times: FloatArray, cert: SeparationCertificate, n_segments: int | None = None) -> SeparationRows:
    """The rows n . a_k <= c - s'/2 of every certificate interval (A's side: ours) on our
    segments of span `times` (m,): each interval cut at our knots, each piece's 10 control points
    a fixed combination (de Casteljau blossom) of its segment's. After our end (a hold), the row
    is on our last control point."""
    m1 = times.size - 1 if n_segments is None else n_segments
    knots = _merge_knots(np.concatenate([cert.times, times[(times > cert.times[0]) & (times < cert.times[-1])]]))
    t0, t1 = knots[:-1], knots[1:]
    mid = 0.5 * (t0 + t1)
    which = np.clip(np.searchsorted(cert.times, mid, side="right") - 1, 0, cert.n_intervals - 1)
    seg = np.clip(np.searchsorted(times, mid, side="right") - 1, 0, m1 - 1)
    d = times[seg + 1] - times[seg]
    u0 = np.clip((t0 - times[seg]) / d, 0.0, 1.0)
    u1 = np.clip((t1 - times[seg]) / d, 0.0, 1.0)
    eye = np.broadcast_to(np.eye(10), (t0.size, 10, 10))
    w = restrict(eye, u0, u1)  # (K, 10 piece points, 10 segment points)
    held = t0 >= times[-1] - KNOT_TOL
    if held.any():
        w[held] = 0.0
        w[held, :, 9] = 1.0
    scale = np.linalg.norm(cert.normals, axis=1)
    n = cert.normals / scale[:, None]
    rhs = cert.offsets / scale - 0.5 * cert.required
    kk = t0.size
    return SeparationRows(np.repeat(seg, 10).astype(np.intp), w.reshape(kk * 10, 10), np.repeat(n[which], 10, axis=0),
                          np.repeat(rhs[which], 10))


def _others_pieces(others: Sequence[Trajectory], owner: IntArray, t0: FloatArray, t1: FloatArray) -> FloatArray:
    """Pieces (K, 10, 3) of others[owner[i]] on [t0[i], t1[i]], one de Casteljau pass for all."""
    seg = np.zeros(t0.size, dtype=np.intp)
    u0, u1 = np.zeros(t0.size), np.zeros(t0.size)
    held = np.zeros(t0.size, dtype=bool)
    ctrl = np.empty((t0.size, 10, 3))
    for j in np.unique(owner).tolist():
        rows = np.flatnonzero(owner == j)
        seg[rows], u0[rows], u1[rows], held[rows] = _locate(others[j], t0[rows], t1[rows])
        ctrl[rows] = others[j].control_points[seg[rows]]
    out = restrict(ctrl, u0, u1)
    for i in np.flatnonzero(held).tolist():
        out[i] = others[int(owner[i])].control_points[-1, -1]
    return out


def planning_rows(times: FloatArray, reference: Trajectory, neighbours: Neighbours, pieces: int = 2,
                  max_depth: int = 3) -> SeparationRows:
    """Time-resolved rows for planning on our segments of span `times` (m,): our reference (the
    previous plan, or the straight segments at these times) and each near neighbour are split at
    the union of their knots and ours, each common interval into `pieces` equal pieces; per piece
    a plane (an axis or centroid plane where it clears s', else the max-margin plane) and the rows
    n . a_k <= min_k n . b_k - s' on our piece's 10 control points (each a fixed combination of
    its segment's). A piece whose best plane leaves our reference within s' of the neighbour is
    halved (up to `max_depth` times) so that the plan may pass at another time. Pieces whose
    neighbour is farther than s' + reach from our reference get no row. Unlike `neighbour_faces` (one plane per segment), a neighbour may cross our path within
    one of our segments, at another time. Every pair is split in one batch."""
    empty = SeparationRows(np.zeros(0, dtype=np.intp), np.zeros((0, 10)), np.zeros((0, 3)), np.zeros(0))
    if not neighbours.trajectories:
        return empty
    m1 = times.size - 1
    qlo, qhi = space_time_boxes(reference)
    olo, ohi, owner_box = neighbours.boxes
    _, bk = near_pairs(qlo[:-1], qhi[:-1], olo, ohi, neighbours.max_required + neighbours.reach)
    near = sorted(set(owner_box[bk].tolist()))
    if not near:
        return empty
    span = (float(times[0]), float(times[-1]))
    frac = np.arange(pieces + 1) / pieces
    t0_l: list[FloatArray] = []
    t1_l: list[FloatArray] = []
    own_l: list[IntArray] = []
    for k in near:
        knots = common_knots(reference, neighbours.trajectories[k], extra=times, span=span)
        if knots.size < 2:
            continue
        edges = knots[:-1, None] + (knots[1:] - knots[:-1])[:, None] * frac[None, :]  # (K, pieces + 1)
        t0_l.append(edges[:, :-1].ravel())
        t1_l.append(edges[:, 1:].ravel())
        own_l.append(np.full(t0_l[-1].size, k, dtype=np.intp))
    if not t0_l:
        return empty
    t0, t1, owner = np.concatenate(t0_l), np.concatenate(t1_l), np.concatenate(own_l)
    need = np.array([neighbours.required(k) for k in range(len(neighbours.trajectories))])[owner]
    pa = _pieces(reference, t0, t1)
    pb = _others_pieces(neighbours.trajectories, owner, t0, t1)
    halves = _halves()
    out_t0: list[FloatArray] = []
    out_t1: list[FloatArray] = []
    out_n: list[FloatArray] = []
    out_rhs: list[FloatArray] = []
    for level in range(max_depth + 1):
        n, gap, _ = _cheap_planes(pa, pb)
        keep = gap < need + neighbours.reach  # farther pieces need no row
        for i in np.flatnonzero(keep & (gap < need)).tolist():
            mm = max_margin_plane(pa[i], pb[i])
            if mm is not None and mm[1] > gap[i]:
                n[i], gap[i] = mm[0], mm[1]
        # where even the best plane leaves our reference within s', halve both pieces (exactly)
        # and look again: finer pieces give the plan room to pass at another time
        split = keep & (gap < need) & (level < max_depth)
        done = keep & ~split
        out_t0.append(t0[done])
        out_t1.append(t1[done])
        out_n.append(n[done])
        out_rhs.append(np.einsum("kx,kpx->kp", n[done], pb[done]).min(axis=1) - need[done])
        if not split.any():
            break
        tm = 0.5 * (t0[split] + t1[split])
        t0 = np.concatenate([t0[split], tm])
        t1 = np.concatenate([tm, t1[split]])
        need = np.concatenate([need[split], need[split]])
        pa = np.concatenate([np.matmul(halves[0], pa[split]), np.matmul(halves[1], pa[split])])
        pb = np.concatenate([np.matmul(halves[0], pb[split]), np.matmul(halves[1], pb[split])])
    t0, t1 = np.concatenate(out_t0), np.concatenate(out_t1)
    if t0.size == 0:
        return empty
    idx = np.arange(t0.size)
    n = np.concatenate(out_n).reshape(-1, 3)
    rhs = np.concatenate(out_rhs)
    tm = 0.5 * (t0[idx] + t1[idx])
    seg = np.clip(np.searchsorted(times, tm, side="right") - 1, 0, m1 - 1)
    d = times[seg + 1] - times[seg]
    u0 = np.clip((t0[idx] - times[seg]) / d, 0.0, 1.0)
    u1 = np.clip((t1[idx] - times[seg]) / d, 0.0, 1.0)
    w = restrict(np.broadcast_to(np.eye(10), (idx.size, 10, 10)), u0, u1)  # (P, 10, 10)
    return SeparationRows(np.repeat(seg, 10).astype(np.intp), w.reshape(-1, 10), np.repeat(n[idx], 10, axis=0),
                          np.repeat(rhs, 10))


def reference_trajectory(problem: Problem, reference: Trajectory | None) -> Trajectory:
    """Our reference in time: the previous plan where given, else the straight segments between
    the problem's waypoints at its times."""
    if reference is not None:
        return reference
    return Trajectory(problem.times.copy(), straight_reference(problem))
