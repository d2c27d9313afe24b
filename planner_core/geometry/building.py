"""Building every corridor of a route (`build_corridors`): validation, the broad phase over
analysis boxes, one plane per candidate obstacle nearest first, then pruning. See the package
docstring for the rules it keeps."""


from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from planner_core.broadphase import count_beyond, overlapping_pairs
from planner_core.facets import facet_masks
from planner_core.geometry.common import CERT_TOL, BoolArray, CorridorError, IntArray
from planner_core.geometry.obstacles import (
    Obstacles,
    analysis_box,
    map_planes,
    min_over_vertices,
    pair_point_distance,
    prepare_obstacles,
)
from planner_core.geometry.polytopes import FRAME_A, as_points
from planner_core.geometry.pruning import (
    first_of_duplicates_padded,
    greedy_planes,
    mutual_certificates,
    prune_planes,
    restore_certificates,
)
from planner_core.geometry.separating import separation, separations_padded
from planner_core.problem import FloatArray, Polytope

DEFAULT_INFLUENCE_MARGIN = 3.0  # metres: the analysis box pads the segment by its length plus this
_PAIR_BATCH = 1_000_000  # (segment, obstacle) pairs x per-pair work per batch (bounds the temporaries)


@dataclass(frozen=True)
class BuildContext:
    waypoints: FloatArray
    obs: Obstacles
    radius: float
    map_A: FloatArray
    map_b: FloatArray
    aux: tuple[FloatArray, FloatArray] | None
    first_index: int  # index of obs[0] in the caller's numbering


def validate_waypoints(waypoints: ArrayLike) -> FloatArray:
    wps = as_points(waypoints, "waypoints")
    if wps.shape[0] < 2:
        raise ValueError(f"waypoints: need at least 2, got {wps.shape[0]}")
    return wps


def validate_radius(radius: float) -> float:
    r = float(radius)
    if not np.isfinite(r) or r < 0.0:
        raise ValueError(f"radius: must be finite and >= 0, got {radius}")
    return r


def _check_waypoints_in_map(ctx: BuildContext) -> None:
    if ctx.map_A.shape[0] == 0:
        return
    excess = ctx.waypoints @ ctx.map_A.T - ctx.map_b  # (m, 6)
    bad = np.flatnonzero(np.any(excess > 0.0, axis=1))
    if bad.size:
        i = int(bad[0])
        raise CorridorError(
            f"waypoint {i} {ctx.waypoints[i].tolist()} is outside the map box shrunk by "
            f"radius {ctx.radius:g} (by {float(np.max(excess[i])):.3g})",
            waypoint=i,
        )


def _point_distance(point: FloatArray, ctx: BuildContext, k: int) -> float:
    """Distance from a point to obstacle k (0 if inside)."""
    normal, gap = separation(point[None, :], ctx.obs.verts[k])
    return 0.0 if normal is None else max(gap, 0.0)


def check_waypoints_clear(ctx: BuildContext, pairs: tuple[IntArray, IntArray] | None = None) -> None:
    """CorridorError for the first waypoint (then obstacle) inside an obstacle inflated by r.

    pairs: the (waypoint, obstacle) pairs to examine, sorted (default: all); any pair
    left out must be known to be clear.
    """
    obs = ctx.obs
    if obs.n == 0:
        return
    if pairs is None:
        near = (
            np.linalg.norm(ctx.waypoints[:, None, :] - obs.centres[None, :, :], axis=-1) - obs.radii
            < ctx.radius
        )
        wi, wk = np.nonzero(near)
    else:
        wi, wk = pairs
        close = np.linalg.norm(ctx.waypoints[wi] - obs.centres[wk], axis=1) - obs.radii[wk] < ctx.radius
        wi, wk = wi[close], wk[close]
    for i, k in zip(wi.tolist(), wk.tolist(), strict=True):
        A, b = obs.planes[k]
        if float(np.max(A @ ctx.waypoints[i] - b)) >= ctx.radius:
            continue  # one face plane already keeps it radius away
        dist = _point_distance(ctx.waypoints[i], ctx, int(k))
        if dist < ctx.radius:
            raise CorridorError(
                f"waypoint {i} {ctx.waypoints[i].tolist()} is inside obstacle "
                f"{ctx.first_index + k} inflated by radius {ctx.radius:g} "
                f"(distance {dist:.3g})",
                waypoint=int(i),
                obstacle=ctx.first_index + int(k),
            )


def blocked_error(ctx: BuildContext, j: int, k: int, gap: float) -> CorridorError:
    seg = ctx.waypoints[j : j + 2]
    kk = ctx.first_index + k
    r = ctx.radius
    why = f"gap {gap:.3g} < 2 x radius" if gap > 0.0 else "the segment passes through it"
    close = [j + e for e in (0, 1) if _point_distance(seg[e], ctx, k) < 2.0 * r]
    extra = f"; waypoint {close[0]} is within 2 x radius of it" if close else ""
    return CorridorError(
        f"segment {j} (waypoint {j} -> {j + 1}) is blocked by obstacle {kk} inflated by "
        f"radius {r:g} ({why}){extra}",
        segment=j,
        waypoint=close[0] if close else None,
        obstacle=kk,
    )


Separation = tuple[FloatArray | None, float]  # (unit normal or None if they meet, gap)


def separation_arrays(ctx: BuildContext, js: IntArray, ks: IntArray) -> tuple[FloatArray, FloatArray]:
    """Max-margin normals (p, 3; NaN where they meet) and gaps (p,) of the pairs
    (segment js[i], obstacle ks[i]), all in one batch."""
    if js.shape[0] == 0 or ctx.obs.shapes is None:
        return np.full((js.shape[0], 3), np.nan), np.zeros(js.shape[0])
    sh = ctx.obs.shapes
    step = max(1, _PAIR_BATCH // (sh.A.shape[1] ** 2 + sh.edge0.shape[1] + sh.verts.shape[1]))
    parts = [
        separations_padded(ctx.waypoints[js[i : i + step]], ctx.waypoints[js[i : i + step] + 1], sh, ks[i : i + step])
        for i in range(0, js.shape[0], step)
    ]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def pair_separations(ctx: BuildContext, js: IntArray, ks: IntArray) -> dict[tuple[int, int], Separation]:
    normals, gaps = separation_arrays(ctx, js, ks)
    return {
        (j, k): (None if np.isnan(n[0]) else n, g)
        for j, k, n, g in zip(js.tolist(), ks.tolist(), normals, gaps.tolist(), strict=True)
    }


def _obstacle_plane(ctx: BuildContext, j: int, k: int, sep: Separation | None = None) -> tuple[FloatArray, float]:
    """The roomiest safe plane (unit a, offset) between segment j and obstacle k."""
    verts = ctx.obs.verts[k]
    if sep is None:
        sep = pair_separations(ctx, np.array([j]), np.array([k]))[(j, k)]
    normal, gap = sep
    if normal is None or gap < 2.0 * ctx.radius:
        raise blocked_error(ctx, j, k, gap)
    return normal, float(np.min(verts @ normal)) - ctx.radius


def add_planes(
    ctx: BuildContext,
    j: int,
    A: FloatArray,
    b: FloatArray,
    candidates: IntArray,
    must: BoolArray,
    seps: dict[tuple[int, int], Separation] | None = None,
) -> tuple[FloatArray, FloatArray]:
    """Add a plane for each candidate obstacle (nearest first) that needs one.

    must[k]: obstacle k gets its own plane even if already certified.
    seps: separations computed beforehand in a batch (others are computed here).
    """
    certs = ctx.obs.margins(A, b)
    certified = np.any(certs >= ctx.radius - CERT_TOL, axis=1)
    new_A: list[FloatArray] = []
    new_b: list[float] = []
    for k in candidates:
        if certified[k] and not must[k]:
            continue
        a, off = _obstacle_plane(ctx, j, int(k), None if seps is None else seps.get((j, int(k))))
        new_A.append(a)
        new_b.append(off)
        certified |= ctx.obs.margins(a[None, :], np.array([off]))[:, 0] >= ctx.radius - CERT_TOL
    if not new_A:
        return A, b
    return np.concatenate([A, np.stack(new_A)]), np.concatenate([b, np.array(new_b)])


def finish_corridor(ctx: BuildContext, A: FloatArray, b: FloatArray) -> Polytope:
    keep = prune_planes(A, b, ctx.obs.margins(A, b), ctx.radius, ctx.aux)
    return Polytope(A=np.ascontiguousarray(A[keep]), b=np.ascontiguousarray(b[keep]))


def build_context(
    wps: FloatArray,
    obs: Obstacles,
    map_box: tuple[ArrayLike, ArrayLike] | None,
    radius: float,
    first_index: int = 0,
    all_obs: Obstacles | None = None,
) -> BuildContext:
    map_A, map_b = map_planes(map_box, radius)
    aux = None if map_box is not None else analysis_box(wps, all_obs if all_obs is not None else obs)
    return BuildContext(wps, obs, radius, map_A, map_b, aux, first_index)


def build_corridors(
    waypoints: ArrayLike,
    obstacles: Sequence[Polytope],
    map_box: tuple[ArrayLike, ArrayLike] | None,
    radius: float,
    *,
    influence: float | None = None,
) -> tuple[Polytope, ...]:
    """One safe convex corridor per segment (see the module docstring for the rules).

    influence: how far the segment's analysis box reaches beyond the segment's
    bounding box; default segment length + 3 m, never below 2 x radius + 0.5 m.
    Obstacles meeting the box (inflated by radius) are candidates: nearest first, each
    gets a plane unless a nearer one's plane already keeps it radius away; the box's
    faces exclude the others.
    Raises CorridorError for a waypoint outside the map box shrunk by radius,
    a waypoint inside an inflated obstacle, or a blocked segment; ValueError
    for malformed input.
    """
    wps = validate_waypoints(waypoints)
    r = validate_radius(radius)
    if influence is not None and not (np.isfinite(influence) and influence >= 0.0):
        raise ValueError(f"influence: must be finite and >= 0, got {influence}")
    obs = prepare_obstacles(obstacles)
    map_A, map_b = map_planes(map_box, r)
    ctx = BuildContext(wps, obs, r, map_A, map_b, None, 0)
    _check_waypoints_in_map(ctx)
    p0, p1 = wps[:-1], wps[1:]
    lengths = np.linalg.norm(p1 - p0, axis=1)
    reach = lengths + DEFAULT_INFLUENCE_MARGIN if influence is None else np.full_like(lengths, influence)
    flo, fhi = analysis_boxes(p0, p1, np.maximum(reach, 2.0 * r + _MIN_PAD), map_box, r)
    # broad phase: an obstacle that no face of the analysis box keeps r away is a candidate
    js, ks = overlapping_pairs(flo - (r - CERT_TOL), fhi + (r - CERT_TOL), obs.lo, obs.hi)
    # a waypoint inside an inflated obstacle makes it a candidate of the waypoint's segments
    wi = np.concatenate([js, js + 1])
    wk = np.concatenate([ks, ks])
    key = np.unique(wi * max(obs.n, 1) + wk)
    check_waypoints_clear(ctx, (key // max(obs.n, 1), key % max(obs.n, 1)))
    lower = np.maximum(pair_point_distance(p0[js], p1[js], obs.centres[ks]) - obs.radii[ks], 0.0)
    order = np.lexsort((ks, lower, js))  # by segment, nearest first (as the sequential rule)
    js, ks = js[order], ks[order]
    normals, gaps = separation_arrays(ctx, js, ks)
    bad = np.isnan(normals[:, 0]) | (gaps < 2.0 * r)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise blocked_error(ctx, int(js[i]), int(ks[i]), float(gaps[i]))
    offsets = min_over_vertices(obs, normals, ks) - r
    return _assemble(obs, r, flo, fhi, js, ks, normals, offsets)


_MIN_PAD = 0.5  # metres: the analysis box never hugs the segment closer than 2 r + this


def analysis_boxes(
    p0: FloatArray, p1: FloatArray, pad: FloatArray, map_box: tuple[ArrayLike, ArrayLike] | None, radius: float
) -> tuple[FloatArray, FloatArray]:
    """(lo, hi) (s, 3) of each segment's analysis box: its bounding box padded by pad (s,),
    clipped to the map box shrunk by radius. Its six faces are the first six planes of
    the segment's corridor, before pruning."""
    lo = np.minimum(p0, p1) - pad[:, None]
    hi = np.maximum(p0, p1) + pad[:, None]
    if map_box is not None:
        _, map_b = map_planes(map_box, radius)
        hi = np.minimum(hi, map_b[:3])
        lo = np.maximum(lo, -map_b[3:])
    return lo, hi


def _assemble(
    obs: Obstacles,
    r: float,
    flo: FloatArray,
    fhi: FloatArray,
    js: IntArray,
    ks: IntArray,
    normals: FloatArray,
    offsets: FloatArray,
) -> tuple[Polytope, ...]:
    """Each segment's corridor from its analysis box and its candidates' planes (pairs sorted
    by segment, nearest first), in batches of corridors with as many candidates, then with as
    many planes.

    A candidate gets its plane unless a nearer candidate's plane already keeps it r away (the
    greedy rule, one rank at a time for every corridor at once). Pruning then keeps the facets;
    a face of the analysis box also while some obstacle lies wholly beyond it (it is their
    certificate: counted with a sorted sweep, none examined), and a candidate's plane also
    when it is the certificate a candidate would lose.
    """
    n_seg = flo.shape[0]
    fb = np.concatenate([fhi, -flo], axis=1)  # (s, 6)
    far = np.zeros((n_seg, 6), dtype=bool)
    if obs.n:
        for a in range(3):
            far[:, a] = count_beyond(obs.lo[:, a], fhi[:, a] + (r - CERT_TOL), upper=True) > 0
            far[:, 3 + a] = count_beyond(obs.hi[:, a], flo[:, a] - (r - CERT_TOL), upper=False) > 0
    counts = np.bincount(js, minlength=n_seg)
    first = np.concatenate([[0], np.cumsum(counts)[:-1]])
    V = 0 if obs.shapes is None else obs.shapes.verts.shape[1]
    # per corridor: the rows (into the pairs) of the planes it takes, and which candidate
    # certifies which (both for the pruning's certificate restoration)
    taken: list[IntArray] = [np.zeros(0, dtype=np.intp)] * n_seg
    certs: list[BoolArray] = [np.zeros((0, 0), dtype=bool)] * n_seg
    for K in np.unique(counts).tolist():
        if K == 0 or obs.shapes is None:
            continue
        every = np.flatnonzero(counts == K)
        step = max(1, _PAIR_BATCH // (K * K * V))
        for i in range(0, every.shape[0], step):
            segs = every[i : i + step]
            pidx = first[segs][:, None] + np.arange(K)[None, :]  # (G, K)
            cert = mutual_certificates(obs.shapes.verts[ks[pidx]], normals[pidx], offsets[pidx], r)
            added = greedy_planes(cert)
            for g, j in enumerate(segs.tolist()):
                taken[j] = pidx[g, added[g]]
                certs[j] = cert[g][:, added[g]]  # (K candidates, planes taken)
    n_taken = np.array([t.shape[0] for t in taken], dtype=np.intp)
    out: list[Polytope | None] = [None] * n_seg
    for Q in np.unique(n_taken).tolist():
        every = np.flatnonzero(n_taken == Q)
        step = max(1, _PAIR_BATCH // ((6 + Q) ** 2 * 64))
        for i in range(0, every.shape[0], step):
            segs = every[i : i + step]
            rows = np.stack([taken[j] for j in segs.tolist()]) if Q else np.zeros((segs.shape[0], 0), dtype=np.intp)
            G = segs.shape[0]
            A = np.concatenate([np.broadcast_to(FRAME_A, (G, 6, 3)), normals[rows]], axis=1)
            b = np.concatenate([fb[segs], offsets[rows]], axis=1)
            distinct = first_of_duplicates_padded(A, b, np.ones((G, 6 + Q), dtype=bool))
            keep = distinct & facet_masks(A, b)
            keep[:, :6] |= far[segs]
            if Q:
                restore_certificates(keep[:, 6:], distinct[:, 6:], [certs[j] for j in segs.tolist()])
            for g, j in enumerate(segs.tolist()):
                out[j] = Polytope(A=np.ascontiguousarray(A[g, keep[g]]), b=np.ascontiguousarray(b[g, keep[g]]))
    return tuple(p for p in out if p is not None)
