"""The separation certificate between two committed trajectories: one plane per common interval,
made by `certify_separation` / `certify_many` and checked by `verify_separation` (what any receiver
runs). The method is told in `planner_core.separation`; the pieces and planes come from
`planner_core.separation_pieces`.

Pure numpy (plus daqp for the small max-margin QPs); no I/O.
"""

from __future__ import annotations

import enum
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from planner_core.bezier import segments_at
from planner_core.problem import FloatArray, Trajectory
from planner_core.separation_batch import (
    Packed,
    batch_knots,
    locate_packed,
    our_boxes,
    pack,
    span_boxes,
)
from planner_core.separation_pieces import (
    AXES,
    GILBERT_MIN,
    KNOT_TOL,
    IntArray,
    best_plane,
    cheap_planes,
    common_pieces,
    halves_matrix,
    max_margin_plane,
    nearest_planes,
    overlap,
    peak_speed,
    restrict,
    speed_bound,
)

MAX_DEPTH = 4  # an interval whose margin is short is halved up to this many times (16 pieces)
SPAN_BOXES_MIN = 16  # fewer short intervals than this: straight to the pieces (the runs cost more)


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
    if speeds is None:
        sa = speed_bound(a) if clock_tolerance > 0.0 else 0.0
        sp = [(sa, speed_bound(b) if clock_tolerance > 0.0 else 0.0) for b in others]
    else:
        sp = [(float(x), float(y)) for x, y in speeds]
    return certify_packed(a, pack(others), np.arange(len(others), dtype=np.intp), separation,
                          clock_tolerance=clock_tolerance, speeds=sp, max_depth=max_depth, exact=exact, span=span)


def certify_packed(
    a: Trajectory,
    p: Packed,
    owners: IntArray,
    separation: float,
    *,
    clock_tolerance: float,
    speeds: Sequence[tuple[float, float]],
    max_depth: int = MAX_DEPTH,
    exact: bool = False,
    span: tuple[float, float] | None = None,
) -> list[SeparationCheck]:
    """`certify_many` against the stacked trajectories p[owners[j]] with bound speeds speeds[j]
    (`certify_all` keeps its neighbours stacked: nothing is gathered per call)."""
    owners = np.asarray(owners, dtype=np.intp)
    nk = owners.size
    if nk == 0:
        return []
    sp = [(float(x), float(y)) for x, y in speeds]
    needs = np.array([separation + (va + vb) * clock_tolerance for va, vb in sp], dtype=float)
    pair, k0, k1, counts = batch_knots(a, p, owners, span)
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.intp)
    need = needs[pair]
    # boxes first (no splitting): of the two whole segments; where that is short, ours over the
    # run of our segment's grid holding the interval (`span_boxes`)
    alo, ahi, a_seg, a_u0, a_u1, a_held = our_boxes(a, k0, k1)
    who = owners[pair]
    b_row, b_u0, b_u1, b_held = locate_packed(p, who, k0, k1)
    blo, bhi = p.lo[b_row], p.hi[b_row]
    blo[b_held] = bhi[b_held] = p.last[who[b_held]]
    gaps = np.concatenate([blo - ahi, alo - bhi], axis=1)
    mids = np.concatenate([0.5 * (ahi + blo), -0.5 * (alo + bhi)], axis=1)
    best = np.argmax(gaps, axis=1)
    r = np.arange(k0.size)
    cheap_n, cheap_gap, cheap_c = AXES[best], gaps[r, best], mids[r, best]
    todo = r if exact else np.flatnonzero(cheap_gap < need)
    if todo.size >= SPAN_BOXES_MIN and not exact:
        slo, shi = span_boxes(a, a_seg[todo], a_u0[todo], a_u1[todo], a_held[todo])
        gaps = np.concatenate([blo[todo] - shi, slo - bhi[todo]], axis=1)
        best = np.argmax(gaps, axis=1)
        rt = np.arange(todo.size)
        better = gaps[rt, best] > cheap_gap[todo]
        mids = np.concatenate([0.5 * (shi + blo[todo]), -0.5 * (slo + bhi[todo])], axis=1)
        up = todo[better]
        cheap_n[up], cheap_gap[up], cheap_c[up] = AXES[best[better]], gaps[rt, best][better], mids[rt, best][better]
        todo = todo[cheap_gap[todo] < need[todo]]
    pa = np.zeros((k0.size, 10, 3))
    pb = np.zeros((k0.size, 10, 3))
    if todo.size:
        # ours and theirs in one de Casteljau pass
        both = restrict(np.concatenate([a.control_points[a_seg[todo]], p.ctrl[b_row[todo]]]),
                        np.concatenate([a_u0[todo], b_u0[todo]]), np.concatenate([a_u1[todo], b_u1[todo]]))
        pa[todo], pb[todo] = both[: todo.size], both[todo.size :]
        pa[todo[a_held[todo]]] = a.control_points[-1, -1]
        held = todo[b_held[todo]]
        pb[held] = p.last[who[held]][:, None]
        cn, cg, cc = cheap_planes(pa[todo], pb[todo])
        better = cg > cheap_gap[todo]
        cheap_n[todo[better]], cheap_gap[todo[better]], cheap_c[todo[better]] = cn[better], cg[better], cc[better]
    if exact:
        return [assemble_certificate(np.append(k0[lo:hi], k1[hi - 1]) if hi > lo else k0[:0], lo, cheap_n, cheap_gap,
                                     cheap_c, pa, pb, float(needs[j]), separation, clock_tolerance, sp[j], max_depth,
                                     True)
                for j, (lo, hi) in enumerate(zip(starts[:-1].tolist(), starts[1:].tolist(), strict=True))]
    # the intervals the cheap planes leave short, all at once: Gilbert's steps, the QP only where
    # they settle nothing, halving where even the best plane is short
    short = np.flatnonzero(cheap_gap < need)
    first_fail: dict[int, int] = {}
    fail_pts = None
    if short.size == 0:
        # every interval cleared as it stands: the certificates are the intervals in order
        it_t0, it_n, it_c, it_gap, it_start = k0, cheap_n, cheap_c, cheap_gap, starts
        n_eval = short
    else:
        acc, fail, n_eval, fail_pts = settle(short, k0[short], k1[short], pa[short], pb[short], need[short],
                                             max_depth)
        easy = np.flatnonzero(cheap_gap >= need)
        it_pair = np.concatenate([pair[easy], pair[acc.idx]])
        it_t0 = np.concatenate([k0[easy], acc.t0])
        it_n = np.concatenate([cheap_n[easy], acc.n])
        it_c = np.concatenate([cheap_c[easy], acc.c])
        it_gap = np.concatenate([cheap_gap[easy], acc.gap])
        order = np.lexsort((it_t0, it_pair))
        it_pair, it_t0, it_n, it_c, it_gap = it_pair[order], it_t0[order], it_n[order], it_c[order], it_gap[order]
        it_start = np.concatenate([[0], np.cumsum(np.bincount(it_pair, minlength=nk))]).astype(np.intp)
        # each failing pair's first failure in time order (interval, then piece): what certifying
        # pair by pair would have stopped at
        if fail.idx.size:
            fo = np.lexsort((fail.t0, fail.idx))
            fp = pair[fail.idx[fo]]
            _, at = np.unique(fp, return_index=True)
            first_fail = {int(fp[i]): int(fo[i]) for i in at.tolist()}
    qps = np.bincount(pair[n_eval], minlength=nk) if n_eval.size else np.zeros(nk, dtype=np.intp)
    out: list[SeparationCheck] = []
    for j in range(nk):
        lo, hi = int(starts[j]), int(starts[j + 1])
        ilo, ihi = int(it_start[j]), int(it_start[j + 1])
        if hi == lo:
            out.append(SeparationCheck(SeparationStatus.OK, None, message="no overlap within the span"))
            continue
        if j in first_fail:
            f = first_fail[j]
            i = int(fail.idx[f]) - lo
            before = ilo + int(np.searchsorted(it_t0[ilo:ihi], fail.t0[f], side="left"))
            low = float(it_gap[ilo:before].min()) if before > ilo else np.inf
            gap, t0, t1 = float(fail.gap[f]), float(fail.t0[f]), float(fail.t1[f])
            if fail_pts is not None:  # (set whenever a piece failed)
                # the hull gap named is the max-margin one (skipped where no plane could clear s')
                mm = max_margin_plane(fail_pts[0][f], fail_pts[1][f])
                gap = max(gap, mm[1]) if mm is not None else gap
            msg = (f"interval {i} [{k0[lo + i]:.6g}, {k1[lo + i]:.6g}] s: the pieces come within "
                   f"{max(gap, 0.0):.4g} m (hull gap) of each other on [{t0:.6g}, {t1:.6g}] s, "
                   f"{needs[j] - gap:.4g} m short of {needs[j]:.4g} m")
            out.append(SeparationCheck(SeparationStatus.TOO_CLOSE, None, i, (float(k0[lo + i]), float(k1[lo + i])),
                                       float(needs[j] - gap), low, msg, {"qps": int(qps[j])}))
            continue
        low = float(it_gap[ilo:ihi].min())
        cert = SeparationCertificate(np.append(it_t0[ilo:ihi], k1[hi - 1]), it_n[ilo:ihi], it_c[ilo:ihi],
                                     float(separation), float(clock_tolerance), sp[j][0], sp[j][1])
        out.append(SeparationCheck(SeparationStatus.OK, cert, min_gap=low,
                                   message=f"separated by >= {low:.4g} m (required {needs[j]:.4g} m) on "
                                   f"{cert.n_intervals} intervals",
                                   stats={"qps": int(qps[j]), "common_intervals": hi - lo}))
    return out


@dataclass(frozen=True)
class Pieces:
    """Pieces of common intervals: the interval each lies in (`idx`), its start and end, and a
    plane (normal, mid-plane c, gap) where one was found."""

    idx: IntArray
    t0: FloatArray
    t1: FloatArray
    n: FloatArray
    c: FloatArray
    gap: FloatArray


def settle(idx: IntArray, t0: FloatArray, t1: FloatArray, qa: FloatArray, qb: FloatArray, need: FloatArray,
           max_depth: int) -> tuple[Pieces, Pieces, IntArray, tuple[FloatArray, FloatArray] | None]:
    """Planes for intervals (t0, t1, our pieces qa, theirs qb) the cheap planes left short of
    `need`, level by level for all at once: axis/centroid planes, Gilbert's steps
    (`nearest_planes`), the max-margin QP only where those neither clear `need` nor prove that no
    plane can; a piece still short is halved (both at the same u, exactly) up to `max_depth`
    times. Returns the accepted pieces, the failed ones (short at `max_depth`), the interval of
    every piece looked at (for the stats) and the failed pieces' points (ours, theirs), if any."""
    halves = halves_matrix()
    empty = (idx[:0], t0[:0], t1[:0], np.zeros((0, 3)), t0[:0], t0[:0])
    acc = [empty]
    bad_out = empty
    bad_pts = None
    seen = [idx]
    for depth in range(max_depth + 1):
        if idx.size == 0:
            break
        n, gap, c = cheap_planes(qa, qb)
        short = np.flatnonzero(gap < need)
        bound = np.full(idx.size, np.inf)
        if short.size >= GILBERT_MIN:
            gn, gg, gc, gb = nearest_planes(qa[short], qb[short], need[short])
            better = gg > gap[short]
            n[short[better]], gap[short[better]], c[short[better]] = gn[better], gg[better], gc[better]
            bound[short] = gb
        for i in np.flatnonzero((gap < need) & (bound >= need)).tolist():
            mm = max_margin_plane(qa[i], qb[i])
            if mm is not None and mm[1] > gap[i]:
                n[i], gap[i], c[i] = mm
        ok = gap >= need
        acc.append((idx[ok], t0[ok], t1[ok], n[ok], c[ok], gap[ok]))
        no = ~ok
        if depth == max_depth or not no.any():
            bad_out = (idx[no], t0[no], t1[no], n[no], c[no], gap[no])
            bad_pts = (qa[no], qb[no]) if no.any() else None
            break
        tm = 0.5 * (t0[no] + t1[no])
        idx = np.concatenate([idx[no], idx[no]])
        t0, t1 = np.concatenate([t0[no], tm]), np.concatenate([tm, t1[no]])
        need = np.concatenate([need[no], need[no]])
        qa = np.concatenate([np.matmul(halves[0], qa[no]), np.matmul(halves[1], qa[no])])
        qb = np.concatenate([np.matmul(halves[0], qb[no]), np.matmul(halves[1], qb[no])])
        seen.append(idx)
    accepted = Pieces(*(np.concatenate(part) for part in zip(*acc, strict=True)))
    return accepted, Pieces(*bad_out), np.concatenate(seen), bad_pts


def assemble_certificate(knots: FloatArray, first: int, cheap_n: FloatArray, cheap_gap: FloatArray,
                         cheap_c: FloatArray, pa: FloatArray, pb: FloatArray, need: float, separation: float,
                         clock_tolerance: float, speeds: tuple[float, float], max_depth: int,
                         exact: bool) -> SeparationCheck:
    """One pair's intervals (rows first.. of the batch) -> its certificate or first failure."""
    if knots.size < 2:
        return SeparationCheck(SeparationStatus.OK, None, message="no overlap within the span")
    halves = halves_matrix()
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
                n, gap, c = mm if mm is not None else best_plane(qa, qb, np.inf)
            else:
                n, gap, c = best_plane(qa, qb, need)
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
            peak = peak_speed(traj)
            if v < peak - 1e-9:
                return SeparationCheck(SeparationStatus.SPEED, cert, shortfall=float((peak - v) * cert.clock_tolerance),
                                       message=f"the bound speed stated for {name} ({v:.4g} m/s) is below its "
                                       f"trajectory's peak speed ({peak:.4g} m/s)")
    knots, pa, pb = common_pieces(a, b, extra=times[(times > lo) & (times < hi)])
    mid = 0.5 * (knots[:-1] + knots[1:])
    which = segments_at(times, mid)
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
