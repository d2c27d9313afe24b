"""Planning against other vehicles' committed trajectories: `Neighbours` (the trajectories and the
rule), the space-time broad phase (`space_time_boxes`, `near_pairs`), one face per segment of ours
(`neighbour_faces`, `with_neighbours`: a corridor face, so the QP stays a QP), time-resolved rows
(`planning_rows`, `separation_rows` -> `SeparationRows`) and `certify_all` (our plan against every
near neighbour). The method is told in `planner_core.separation` (and docs/separation.md).

Pure numpy (plus daqp for the small max-margin QPs); no I/O.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from planner_core.bezier import segments_at
from planner_core.broadphase import overlapping_pairs
from planner_core.problem import Bounds, FloatArray, Polytope, Problem, Trajectory
from planner_core.separation_batch import (
    Packed,
    batch_knots,
    locate_packed,
    our_boxes,
    pack,
    span_boxes,
    span_knots,
)
from planner_core.separation_certificate import (
    SeparationCertificate,
    SeparationCheck,
    certify_packed,
)
from planner_core.separation_pieces import (
    CONVERGED,
    GILBERT_MIN,
    KNOT_TOL,
    IntArray,
    best_plane,
    cheap_planes,
    halves_matrix,
    max_margin_plane,
    merge_knots,
    nearest_planes,
    pieces_on,
    restrict,
    speed_bound,
)

FAR = 1e30  # "for ever" in a time box (a held last point)


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
        # the same trajectories: their stacking and boxes carry over (built here once, so that a
        # caller replanning again and again with the same neighbours never rebuilds them)
        out.__dict__["packed"] = self.packed
        out.__dict__["boxes"] = self.boxes
        out.__dict__["their_speeds"] = self.their_speeds
        return out

    def required(self, k: int) -> float:
        """s' against neighbour k."""
        return float(self.required_all[k])

    @cached_property
    def their_speeds(self) -> FloatArray:
        """Every neighbour's bound speed (`speed_of`), once."""
        return np.array([self.speed_of(k) for k in range(len(self.trajectories))], dtype=float)

    @cached_property
    def required_all(self) -> FloatArray:
        """s' against every neighbour (N,): one array op instead of N calls per use."""
        out: FloatArray = self.separation + (self.our_speed + self.their_speeds) * self.clock_tolerance
        return out

    @cached_property
    def packed(self) -> Packed:
        """The trajectories stacked once (`separation_batch.pack`): every pair in a few array calls."""
        return pack(self.trajectories)

    @cached_property
    def boxes(self) -> tuple[FloatArray, FloatArray, IntArray]:
        """Every neighbour's space-time boxes stacked (`space_time_boxes` of each, in order): (lo, hi,
        owner). Built from `packed` in one pass (one call per neighbour cost ~20 us each)."""
        p = self.packed
        if p.size == 0:
            return np.zeros((0, 4)), np.zeros((0, 4)), np.zeros(0, dtype=np.intp)
        nseg = np.diff(p.rows)
        owner = np.repeat(np.arange(p.size, dtype=np.intp), nseg + 1)
        hold = p.rows[1:] + np.arange(1, p.size + 1)  # the box after each trajectory's segments
        is_seg = np.ones(owner.size, dtype=bool)
        is_seg[hold - 1] = False
        seg_t0 = np.delete(p.times, p.first[1:] - 1)  # every knot but each trajectory's last
        lo = np.empty((owner.size, 4))
        hi = np.empty_like(lo)
        lo[is_seg, 0], hi[is_seg, 0] = seg_t0, np.delete(p.times, p.first[:-1])
        lo[is_seg, 1:], hi[is_seg, 1:] = p.lo, p.hi
        lo[~is_seg, 0], hi[~is_seg, 0] = p.t_end, FAR
        lo[~is_seg, 1:] = hi[~is_seg, 1:] = p.last
        return lo, hi, owner

    @cached_property
    def max_required(self) -> float:
        return float(self.required_all.max()) if self.trajectories else self.separation


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
            out[r] = pieces_on(ref, merge_knots(np.concatenate([[t0, t1], ks]))).reshape(-1, 3)
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
    # one row per (pair, piece of the neighbour over our segment's span), every pair at once: the
    # span from the later start to our segment's end, split at the neighbour's knots
    pq = sorted(set(zip(qi.tolist(), owner[bk].tolist(), strict=True)))
    if not pq:
        return {}
    pq_arr = np.asarray(pq, dtype=np.intp).reshape(-1, 2)
    packed = neighbours.packed
    s_of = sa[pq_arr[:, 0]]
    pp, k0, k1, count = span_knots(np.maximum(times[s_of], packed.t0[pq_arr[:, 1]]), times[s_of + 1], packed,
                                   pq_arr[:, 1])
    if pp.size == 0:
        return {}
    # pairs whose span is empty (the neighbour starts after our segment) are dropped, as before
    kept = np.flatnonzero(count > 0)
    renum = np.full(len(pq), -1, dtype=np.intp)
    renum[kept] = np.arange(kept.size)
    pp = renum[pp]
    pairs = [pq[i] for i in kept.tolist()]
    piece_owner = pq_arr[kept, 1][pp]
    row, u0, u1, held = locate_packed(packed, piece_owner, k0, k1)
    pieces = restrict(packed.ctrl[row], u0, u1)
    pieces[held] = packed.last[piece_owner[held]][:, None]
    # cheap planes for every pair at once (pad each pair's points by repeating its first piece)
    count = np.bincount(pp, minlength=len(pairs))
    width = int(count.max())
    first = np.concatenate([[0], np.cumsum(count)[:-1]])
    slot = np.arange(k0.size) - first[pp]
    padded = np.repeat(pieces[first][:, None], width, axis=1)  # (pairs, width, 10, 3)
    padded[pp, slot] = pieces
    pts_all = padded.reshape(len(pairs), width * 10, 3)
    n_ref = max(r.shape[0] for r in reference)
    ref_pad = np.stack([r[np.minimum(np.arange(n_ref), r.shape[0] - 1)] for r in reference])
    pair_q = np.array([q for q, _ in pairs], dtype=np.intp)
    pair_k = np.array([k for _, k in pairs], dtype=np.intp)
    cn, cg, _ = cheap_planes(ref_pad[pair_q], pts_all)
    need = neighbours.required_all[pair_k]
    normals = cn.copy()
    # where the cheap planes leave less than `reach` of room: the max-margin direction, by Gilbert's
    # steps for all such pairs at once where they converge, else the QP
    tight = np.flatnonzero(cg < need + neighbours.reach)
    if give_up and tight.size:
        _give_up_first(tight, pairs, reference, pieces, pp, ref_pad[pair_q[tight]], pts_all[tight], need, segs, times)
    converged = np.zeros(tight.size, dtype=bool)
    gn, gg = np.zeros((tight.size, 3)), np.zeros(tight.size)
    if tight.size >= GILBERT_MIN:
        gn, gg, _, gb = nearest_planes(ref_pad[pair_q[tight]], pts_all[tight], None)
        converged = gb - gg <= CONVERGED * np.maximum(gb, 1.0)
    for i, j in enumerate(tight.tolist()):
        if converged[i]:
            normals[j] = gn[i] if gg[i] >= cg[j] else cn[j]
        else:
            q, _ = pairs[j]
            normals[j] = best_plane(reference[q], pieces[pp == j].reshape(-1, 3), np.inf)[0]
    rhs = np.einsum("jpx,jx->jp", pts_all, normals).min(axis=1) - need
    seg_of = np.asarray(segs, dtype=np.intp)[pair_q]
    return {int(s): (normals[seg_of == s], rhs[seg_of == s]) for s in np.unique(seg_of).tolist()}


def _give_up_first(tight: IntArray, pairs: list[tuple[int, int]], reference: Sequence[FloatArray], pieces: FloatArray,
                   pp: IntArray, refs: FloatArray, pts: FloatArray, need: FloatArray, segs: list[int],
                   times: FloatArray) -> None:
    """Raise `NoFace` for the first pair (in order) whose max-margin plane leaves our reference
    within s' of the neighbour, if any. Gilbert's steps clear most pairs at once (a plane with
    s' to spare); the QP decides the rest, in order. In growing chunks, so that an early failure
    (a neighbour crossing our first segment) costs no steps for the pairs after it."""
    at, size = 0, GILBERT_MIN
    while at < tight.size:
        chunk = slice(at, min(at + size, tight.size))
        gg = np.full(chunk.stop - at, -np.inf)
        if chunk.stop - at >= GILBERT_MIN:
            gg = nearest_planes(refs[chunk], pts[chunk], need[tight[chunk]])[1]
        for i, j in enumerate(tight[chunk].tolist()):
            if gg[i] >= need[j]:
                continue
            q, k = pairs[j]
            gap = best_plane(reference[q], pieces[pp == j].reshape(-1, 3), np.inf)[1]
            if gap < need[j]:
                raise NoFace(f"neighbour {k} comes within {max(gap, 0.0):.4g} m of our reference over segment "
                             f"{segs[q]} [{times[segs[q]]:.6g}, {times[segs[q] + 1]:.6g}] s (one plane for the "
                             f"segment; {need[j]:.4g} m required)")
        at, size = chunk.stop, 4 * size


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
    checks = certify_packed(traj, neighbours.packed, np.asarray(near, dtype=np.intp), neighbours.separation,
                            clock_tolerance=neighbours.clock_tolerance,
                            speeds=[(neighbours.our_speed, float(neighbours.their_speeds[k])) for k in near], span=span)
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
    knots = merge_knots(np.concatenate([cert.times, times[(times > cert.times[0]) & (times < cert.times[-1])]]))
    t0, t1 = knots[:-1], knots[1:]
    mid = 0.5 * (t0 + t1)
    which = segments_at(cert.times, mid)
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


def _box_gap(ours: Trajectory, t0: FloatArray, t1: FloatArray, packed: Packed, row: IntArray, held_owner: IntArray,
             held: NDArray[np.bool_], room: FloatArray) -> tuple[FloatArray, tuple[IntArray, FloatArray, FloatArray,
                                                                                NDArray[np.bool_]]]:
    """The largest axis gap between our piece's box and the neighbour's segment box (row `row` of
    `packed`; its held point where `held`) on each interval, and our locations. Our box: the whole
    segment's, then, where that leaves less than `room`, the grid run's (`span_boxes`)."""
    alo, ahi, seg, u0, u1, a_held = our_boxes(ours, t0, t1)
    blo, bhi = packed.lo[row], packed.hi[row]
    blo[held] = bhi[held] = packed.last[held_owner]
    gap = np.maximum((blo - ahi).max(axis=1), (alo - bhi).max(axis=1))
    short = np.flatnonzero(gap < room)
    if short.size:
        slo, shi = span_boxes(ours, seg[short], u0[short], u1[short], a_held[short])
        gap[short] = np.maximum(gap[short], np.maximum((blo[short] - shi).max(axis=1), (slo - bhi[short]).max(axis=1)))
    return gap, (seg, u0, u1, a_held)


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
    owners = np.asarray(near, dtype=np.intp)
    pair, k0, k1, _ = batch_knots(reference, neighbours.packed, owners, span=span, extra=times)
    need_of = neighbours.required_all
    who = owners[pair]
    # an interval (then a piece) whose boxes are s' + reach apart on an axis gives no row (each
    # piece's axis gap is at least its boxes'): skip it before any splitting
    packed = neighbours.packed
    row, _, _, held = locate_packed(packed, who, k0, k1)
    room = need_of[who] + neighbours.reach
    close = _box_gap(reference, k0, k1, packed, row, who[held], held, room)[0] < room
    if not close.any():
        return empty
    k0, k1, owner, row = k0[close], k1[close], who[close], row[close]
    frac = np.arange(pieces + 1) / pieces
    edges = k0[:, None] + (k1 - k0)[:, None] * frac[None, :]  # (K, pieces + 1)
    t0, t1 = edges[:, :-1].ravel(), edges[:, 1:].ravel()
    owner, row = np.repeat(owner, pieces), np.repeat(row, pieces)
    _, u0, u1, held = locate_packed(packed, owner, t0, t1)
    room = need_of[owner] + neighbours.reach
    gap, (seg, a_u0, a_u1, a_held) = _box_gap(reference, t0, t1, packed, row, owner[held], held, room)
    close = gap < room
    if not close.any():
        return empty
    t0, t1, owner, row, u0, u1, held = t0[close], t1[close], owner[close], row[close], u0[close], u1[close], held[close]
    need = need_of[owner]
    both = restrict(np.concatenate([reference.control_points[seg[close]], packed.ctrl[row]]),
                    np.concatenate([a_u0[close], u0]), np.concatenate([a_u1[close], u1]))  # one pass
    pa, pb = both[: t0.size], both[t0.size :]
    pa[a_held[close]] = reference.control_points[-1, -1]
    pb[held] = packed.last[owner[held]][:, None]
    halves = halves_matrix()
    out_t0: list[FloatArray] = []
    out_t1: list[FloatArray] = []
    out_n: list[FloatArray] = []
    out_rhs: list[FloatArray] = []
    for level in range(max_depth + 1):
        n, gap, _ = cheap_planes(pa, pb)
        keep = gap < need + neighbours.reach  # farther pieces need no row
        short = np.flatnonzero(keep & (gap < need))
        bound = np.full(gap.size, np.inf)
        if short.size >= GILBERT_MIN:
            # Gilbert's steps for every short piece at once; the QP only where they fall short
            gn, gg, _, gb = nearest_planes(pa[short], pb[short], need[short])
            better = gg > gap[short]
            n[short[better]], gap[short[better]] = gn[better], gg[better]
            bound[short] = gb
        # the QP where Gilbert's steps settle nothing; below max_depth a piece no plane can clear
        # (bound < s') is halved anyway, so it needs none
        hopeless = (bound < need) & (level < max_depth)
        for i in np.flatnonzero(keep & (gap < need) & ~hopeless).tolist():
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
