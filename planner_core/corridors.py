"""Safe corridors: one convex polytope per segment, built from obstacle polytopes.

A corridor bounds the vehicle *centre* (the planner keeps every control point
of segment j inside corridor j). With vehicle radius r, corridor j = {x : A x <= b}
(unit rows) satisfies, by construction:

- Containment: the straight segment [W_j, W_{j+1}] is inside, at distance >= r
  from every obstacle plane (so the curve has room to bend) and inside the map
  planes (the vehicle centre stays in the map box shrunk by r) and the faces of
  its analysis box (below), which are farther.
- Exclusion (checkable certificate): for every obstacle O there is one corridor
  plane with all vertices of O at signed distance >= r beyond it, so the ball of
  radius r around any corridor point misses O.
- Room: an obstacle's plane has the maximum-margin normal between the segment
  and the obstacle (the hard-margin SVM's normal, which for disjoint convex sets
  is the direction of their closest pair: found in closed form over feature
  pairs, many segments per obstacle at once, see `separations`) and is pushed
  to the obstacle side as far as safety allows: offset = min_v a.v - r. The
  segment then keeps clearance gap - r >= r from it, where gap = min_v a.v -
  max_p a.p is recomputed from the normal (safety never rests on the solver).
- Blocked: a segment is flyable only if the segment inflated by r and the
  obstacle inflated by r are disjoint (gap >= 2r); otherwise CorridorError.
  Obstacles already kept r beyond the shrunk map box count as outside the map.
- Analysis box (the broad phase, the plane choice of this builder): each
  segment's corridor starts as its bounding box padded by `influence` (default
  length + 3 m), clipped to the map box shrunk by r. An obstacle that a face of
  that box already keeps r away (its bounding box lies beyond the face) needs no
  plane: it is never looked at again (`broadphase`: a sorted sweep finds the
  others, the candidates). So a corridor costs what its neighbourhood holds, not
  what the map holds; a far obstacle is excluded by a box face instead of by a
  plane of its own, and never changes the region.
- Economy: the planes of all (segment, candidate) pairs are computed in one
  batch; nearest first, a candidate keeps its plane only when no nearer
  candidate's plane already certifies it (dropping a certified obstacle's plane
  only gives room). Then, for all corridors with as many planes at once
  (`facets`: plane-triple vertices in closed form), planes that are not facets
  are dropped, unless a candidate's plane is the certificate a candidate would
  lose, or a box face has obstacles beyond it (counted with a sorted sweep;
  removing such planes would not change the region, but the certificate is what
  makes exclusion checkable with one matrix product).
- Pop-ups (`update_corridors`): only corridors that no plane (box faces
  included) already certifies against the new obstacle are touched.
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from itertools import combinations
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner_core.broadphase import count_beyond, overlapping_pairs
from planner_core.errors import FieldError
from planner_core.facets import facet_masks, triples
from planner_core.problem import FloatArray, Polytope
from planner_core.qp import SENSE_EQUALITY, DaqpSolver, QPStatus

IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]

CERT_TOL = 1e-10  # slack on the certificate test; the offsets are exact up to rounding
DEFAULT_INFLUENCE_MARGIN = 3.0  # metres: the analysis box pads the segment by its length plus this
_DET_TOL = 1e-12  # unit normals: |det| below this means three planes share no single point
_CHUNK = 20000  # triples per vectorised batch (bounds memory for big hulls)
_PAIR_BATCH = 1_000_000  # (segment, obstacle) pairs x per-pair work per batch (bounds the temporaries)


class CorridorError(FieldError):
    """No safe convex corridor exists; names the segment/waypoint/obstacle at fault.

    A `FieldError` whose message is the description given (unchanged), whose
    `.reason` is that description and whose `.field` is "segments[j]" for a
    blocked segment, else "waypoints[i]" for a waypoint at fault, else "corridors".
    """

    def __init__(
        self,
        message: str,
        *,
        segment: int | None = None,
        waypoint: int | None = None,
        obstacle: int | None = None,
    ) -> None:
        if segment is not None:
            where = f"segments[{segment}]"
        elif waypoint is not None:
            where = f"waypoints[{waypoint}]"
        else:
            where = "corridors"
        super().__init__(where, message, message=message)
        self.segment = segment
        self.waypoint = waypoint
        self.obstacle = obstacle


# --- small geometry helpers -------------------------------------------------


def _as_points(values: ArrayLike, name: str) -> FloatArray:
    pts = np.asarray(values, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (k, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"{name}: contains non-finite values")
    return pts


def _as_point(values: ArrayLike, name: str) -> FloatArray:
    pt = np.asarray(values, dtype=float)
    if pt.shape != (3,) or not np.all(np.isfinite(pt)):
        raise ValueError(f"{name}: expected 3 finite numbers, got {pt.tolist()}")
    return pt


def _triple_chunks(k: int) -> list[IntArray]:
    """All index triples i<j<l of range(k), in batches."""
    if k < 3:
        return []
    if k <= 64:
        return [triples(k)]
    idx = np.fromiter((i for t in combinations(range(k), 3) for i in t), dtype=np.intp)
    idx = idx.reshape(-1, 3)
    return [idx[s : s + _CHUNK] for s in range(0, idx.shape[0], _CHUNK)]


def _unique_rows(x: FloatArray, tol: float) -> FloatArray:
    """Rows of x with near-duplicates removed (snapped to a tol grid; first kept).

    Two rows straddling a grid line may both survive; every caller tolerates
    duplicates, this only keeps the sets small.
    """
    if x.shape[0] <= 1:
        return x
    _, first = np.unique(np.round(x / tol), axis=0, return_index=True)
    return np.asarray(x[np.sort(first)], dtype=float)


def normalised(poly: Polytope, name: str = "polytope") -> tuple[FloatArray, FloatArray]:
    """(A, b) with unit rows; zero rows are rejected (they say nothing or everything)."""
    A = np.asarray(poly.A, dtype=float)
    b = np.asarray(poly.b, dtype=float)
    if A.ndim != 2 or A.shape[1] != 3 or b.shape != (A.shape[0],):
        raise ValueError(f"{name}: A must be (k, 3) and b (k,), got {A.shape} and {b.shape}")
    if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
        raise ValueError(f"{name}: A and b must be finite")
    norms = np.linalg.norm(A, axis=1)
    if np.any(norms <= 1e-12):
        row = int(np.argmax(norms <= 1e-12))
        raise ValueError(f"{name}: row {row} of A is zero")
    return A / norms[:, None], b / norms


def _is_bounded(A: FloatArray) -> bool:
    """True if {x : A x <= b} is bounded (recession cone {d : A d <= 0} is {0})."""
    if A.shape[0] < 4 or np.linalg.matrix_rank(A, tol=1e-9) < 3:
        return False
    i, j = np.triu_indices(A.shape[0], 1)
    rays = np.cross(A[i], A[j])
    norms = np.linalg.norm(rays, axis=1)
    rays = rays[norms > 1e-12] / norms[norms > 1e-12, None]
    # A pointed non-trivial cone has an extreme ray on two of its planes.
    proj = rays @ A.T
    return not bool(np.any(np.all(proj <= 1e-12, axis=1) | np.all(proj >= -1e-12, axis=1)))


def _vertices(A: FloatArray, b: FloatArray) -> FloatArray:
    """Vertices of the bounded polytope {A x <= b} (unit rows) by plane triples."""
    tol = 1e-9 * max(1.0, float(np.max(np.abs(b))))
    found: list[FloatArray] = []
    for idx in _triple_chunks(A.shape[0]):
        M = A[idx]
        ok = np.abs(np.linalg.det(M)) > _DET_TOL
        if not np.any(ok):
            continue
        x = np.linalg.solve(M[ok], b[idx][ok][..., None])[..., 0]
        found.append(x[np.all(x @ A.T <= b + tol, axis=1)])
    if not found:
        return np.zeros((0, 3))
    return _unique_rows(np.concatenate(found), 10 * tol)


# corner c of a box is (hi if bit a of c else lo) on axis a; its 12 edges join corners one bit apart
_CORNER_BITS = (np.arange(8)[:, None] >> np.arange(3)[None, :]) & 1  # (8, 3)
_BOX_EDGES = np.array([(c, c | (1 << a)) for c in range(8) for a in range(3) if not c & (1 << a)], dtype=np.intp)


def _box_extents(A: FloatArray, b: FloatArray) -> tuple[BoolArray, FloatArray, FloatArray]:
    """Which of the polytopes A (n, 6, 3), b (n, 6) (unit rows) are axis-aligned boxes with
    volume (one row per signed axis, in any order), and their (lo, hi) corners (n, 3)."""
    ax = np.argmax(np.abs(A), axis=2)  # (n, 6)
    comp = np.take_along_axis(A, ax[..., None], axis=2)[..., 0]
    ids = ax + 3 * (comp < 0.0)
    axis_rows = np.all((np.abs(comp) == 1.0) & (np.count_nonzero(A, axis=2) == 1), axis=1)
    perm = np.all(np.sort(ids, axis=1) == np.arange(6), axis=1)
    order = np.argsort(ids, axis=1)
    bs = np.take_along_axis(b, order, axis=1)
    hi, lo = bs[:, :3], -bs[:, 3:]
    ok = axis_rows & perm & np.all(hi > lo, axis=1)
    return ok, lo, hi


def _box_corners(lo: FloatArray, hi: FloatArray) -> FloatArray:
    """(n, 8, 3) corners of the boxes [lo, hi] (n, 3), numbered as `_CORNER_BITS`."""
    return np.where(_CORNER_BITS[None].astype(bool), hi[:, None, :], lo[:, None, :])


_VERTEX_CACHE: OrderedDict[tuple[tuple[int, ...], bytes, bytes], FloatArray] = OrderedDict()
_VERTEX_CACHE_SIZE = 256


def polytope_vertices(poly: Polytope, name: str = "polytope") -> FloatArray:
    """Vertices (k, 3) of a bounded, non-empty polytope; ValueError otherwise.

    Results are cached by the exact bytes of (A, b) (read-only arrays): a pop-up
    obstacle is checked when its message is parsed and again by the replan that
    avoids it, and the vertex enumeration is a millisecond or two each time.
    """
    A0 = np.ascontiguousarray(poly.A, dtype=float)
    b0 = np.ascontiguousarray(poly.b, dtype=float)
    key = (A0.shape, A0.tobytes(), b0.tobytes())
    hit = _VERTEX_CACHE.get(key)
    if hit is not None:
        return hit
    A, b = normalised(poly, name)
    if A.shape[0] == 6:
        is_box, lo, hi = _box_extents(A[None], b[None])
        if is_box[0]:
            verts = np.ascontiguousarray(_box_corners(lo, hi)[0])
            verts.flags.writeable = False
            _remember_vertices(poly, verts)
            return verts
    if not _is_bounded(A):
        raise ValueError(f"{name}: polytope is unbounded (its planes do not enclose a region)")
    verts = _vertices(A, b)
    if verts.shape[0] == 0:
        raise ValueError(f"{name}: polytope is empty (its planes have no common point)")
    verts.flags.writeable = False
    _remember_vertices(poly, verts)
    return verts


def _remember_vertices(poly: Polytope, verts: FloatArray) -> None:
    A0 = np.ascontiguousarray(poly.A, dtype=float)
    b0 = np.ascontiguousarray(poly.b, dtype=float)
    _VERTEX_CACHE[(A0.shape, A0.tobytes(), b0.tobytes())] = verts
    while len(_VERTEX_CACHE) > _VERTEX_CACHE_SIZE:
        _VERTEX_CACHE.popitem(last=False)


# --- convex hull (vertices -> H-representation) -----------------------------


def _dedup_planes(A: FloatArray, b: FloatArray, tol: float) -> tuple[FloatArray, FloatArray]:
    if A.shape[0] <= 1:
        return A, b
    key = np.concatenate([A, b[:, None]], axis=1)
    diff = np.max(np.abs(key[:, None, :] - key[None, :, :]), axis=-1)
    keep = ~np.tril(diff <= tol, -1).any(axis=1)
    return A[keep], b[keep]


def _hull_planes(p: FloatArray) -> tuple[FloatArray, FloatArray, IntArray]:
    """Facet planes of the hull of points p (extent ~1), by qhull (O(k log k)), and the
    indices of the points that are hull vertices.

    scipy's ConvexHull triangulates facets, so coplanar triangles give the same plane:
    planes are merged on a 1e-7 grid first (cheap), then pairwise (few left).
    """
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(p)
    except QhullError as exc:  # a degenerate cloud the volume checks let through
        raise ValueError(f"vertices: degenerate hull ({str(exc).splitlines()[0][:80]})") from None
    eq = np.asarray(hull.equations, dtype=float)  # rows (n, -d): n.x - d <= 0 inside
    A = eq[:, :3]
    b = -eq[:, 3]
    key = np.round(np.concatenate([A, b[:, None]], axis=1) / 1e-7)
    _, first = np.unique(key, axis=0, return_index=True)
    keep = np.sort(first)
    A, b = _dedup_planes(A[keep], b[keep], 1e-7)
    return A, b, np.asarray(hull.vertices, dtype=np.intp)


_AXIS_BITS = np.array([1, 2, 4])


def axis_box_of(points: FloatArray) -> tuple[FloatArray, FloatArray] | None:
    """(lo, hi) when the points (k, 3) are exactly the 8 corners of an axis-aligned box with
    volume (in any order, repeats allowed), else None.

    Exact: every coordinate equals its axis' minimum or maximum, and all 8 combinations occur.
    Corners off by a rounding error are not a box here; their hull is (`polytope_from_vertices`
    falls back to it), so the test can only make a box cheaper, never different."""
    if points.ndim != 2 or points.shape[1] != 3 or points.shape[0] < 8:
        return None
    lo, hi = points.min(axis=0), points.max(axis=0)
    if not np.all(hi > lo):
        return None
    at_hi = points == hi
    if not np.all(at_hi | (points == lo)):
        return None
    seen = np.zeros(8, dtype=bool)
    seen[at_hi @ _AXIS_BITS] = True
    return (lo, hi) if bool(seen.all()) else None


SMALL_HULL_POINTS = 12  # up to this many points, the hull by point triples (<= 220 candidate planes)
_HULL_TOL = 1e-9  # on the normalised points (extent 1): a facet plane has every point this far inside


def _small_hull(p: FloatArray) -> tuple[FloatArray, FloatArray, IntArray]:
    """`_hull_planes` for a handful of points (extent ~1, distinct, with volume), without qhull:
    the plane through every triple of points is a facet when all points lie on one side of it;
    coplanar triples' planes are merged as there; a hull vertex is a point on >= 3 facets (one
    on an edge or inside a face is on 2 or 1). The simple obstacle (a prism, a rotated box) skips
    scipy's import and a qhull call for one vectorised pass."""
    t = triples(p.shape[0])
    n = np.cross(p[t[:, 1]] - p[t[:, 0]], p[t[:, 2]] - p[t[:, 0]])
    norm = np.linalg.norm(n, axis=1)
    ok = norm > 1e-9
    n, t = n[ok] / norm[ok, None], t[ok]
    d = np.einsum("td,td->t", n, p[t[:, 0]])
    s = p @ n.T - d[None, :]  # (k, T) signed distances
    below, above = np.all(s <= _HULL_TOL, axis=0), np.all(s >= -_HULL_TOL, axis=0)
    sign = np.where(below, 1.0, -1.0)[below | above]
    A, b = _dedup_planes(n[below | above] * sign[:, None], d[below | above] * sign, 1e-7)
    on = np.abs(p @ A.T - b[None, :]) <= _HULL_TOL
    return A, b, np.flatnonzero(on.sum(axis=1) >= 3).astype(np.intp)


def polytope_from_vertices(vertices: ArrayLike) -> Polytope:
    """H-representation of the convex hull of `vertices` (k, 3).

    Rows of A are unit normals, one per facet (no redundant rows). An axis-aligned box given
    by its corners (`axis_box_of`, the common obstacle) gets its six planes directly, exact;
    a handful of points (<= SMALL_HULL_POINTS) by point triples in one vectorised pass
    (`_small_hull`); more points by qhull (scipy.spatial.ConvexHull): O(k log k), a few ms for
    thousands of points (and scipy's ~0.3 s import once).
    Raises ValueError for fewer than 4 points, non-finite values, or points
    that are collinear or coplanar (the hull would have no volume).
    """
    pts = _as_points(vertices, "vertices")
    if pts.shape[0] < 4:
        raise ValueError(f"vertices: need at least 4 points for a solid hull, got {pts.shape[0]}")
    box = axis_box_of(pts)
    if box is not None:
        lo, hi = box
        poly = Polytope(A=_FRAME_A.copy(), b=np.concatenate([hi, -lo]))
        corners = np.ascontiguousarray(_box_corners(lo[None], hi[None])[0])
        corners.flags.writeable = False
        _remember_vertices(poly, corners)
        return poly
    origin = pts.mean(axis=0)
    scale = float(np.max(np.abs(pts - origin)))
    if scale <= 0.0:
        raise ValueError("vertices: all points coincide (hull has no volume)")
    p = _unique_rows((pts - origin) / scale, 1e-12)
    sv = np.linalg.svd(p - p.mean(axis=0), compute_uv=False)
    if sv.shape[0] < 2 or sv[1] <= 1e-9 * sv[0]:
        raise ValueError("vertices: all points are collinear (hull has no volume)")
    if sv.shape[0] < 3 or sv[2] <= 1e-9 * sv[0]:
        raise ValueError("vertices: all points are coplanar (hull has no volume)")
    A, b, hull_vertices = _small_hull(p) if p.shape[0] <= SMALL_HULL_POINTS else _hull_planes(p)
    if A.shape[0] < 4 or hull_vertices.shape[0] < 4 or not _is_bounded(A):
        A, b, hull_vertices = _hull_planes(p)  # a nearly flat handful: qhull's tolerances decide
    poly = Polytope(A=A, b=b * scale + A @ origin)
    # The hull's vertices are known: `polytope_vertices` need not enumerate plane triples.
    verts = np.ascontiguousarray(p[hull_vertices] * scale + origin, dtype=float)
    verts.flags.writeable = False
    _remember_vertices(poly, verts)
    return poly


def polytope_from_box(center: ArrayLike, size: ArrayLike) -> Polytope:
    """Axis-aligned box of full edge lengths `size` (each > 0) centred at `center`."""
    c = _as_point(center, "center")
    s = np.broadcast_to(np.asarray(size, dtype=float), (3,))
    if not np.all(np.isfinite(s)) or np.any(s <= 0.0):
        raise ValueError(f"size: every edge length must be finite and > 0, got {s.tolist()}")
    eye = np.eye(3)
    return Polytope(A=np.concatenate([eye, -eye]), b=np.concatenate([c + s / 2, -(c - s / 2)]))


# --- queries --------------------------------------------------------------------


def segment_clearance(p0: ArrayLike, p1: ArrayLike, polytope: Polytope) -> float:
    """Smallest distance from the segment [p0, p1] to any plane of `polytope`.

    Positive: the segment is inside with that much room (the largest r for
    which the segment inflated by r stays inside); negative: it pokes out.
    Linear in the segment parameter, so the endpoints decide.
    """
    pts = np.stack([_as_point(p0, "p0"), _as_point(p1, "p1")])
    A, b = normalised(polytope)
    if A.shape[0] == 0:
        return float("inf")
    return float(np.min(b[None, :] - pts @ A.T))


def corridor_contains_segment(
    p0: ArrayLike, p1: ArrayLike, polytope: Polytope, radius: float = 0.0, tol: float = 1e-9
) -> bool:
    """True if the segment inflated by `radius` lies inside `polytope` (up to tol)."""
    return segment_clearance(p0, p1, polytope) >= radius - tol


def exclusion_margin(corridor: Polytope, obstacle_vertices: ArrayLike) -> float:
    """Best single-plane certificate: max over planes of the obstacle's min signed distance.

    A value >= r proves that no point within r of the corridor touches the obstacle.
    """
    verts = _as_points(obstacle_vertices, "obstacle_vertices")
    A, b = normalised(corridor)
    if A.shape[0] == 0:
        return float("-inf")
    return float(np.max(np.min(verts @ A.T - b, axis=0)))


# --- maximum-margin separation -------------------------------------------------


_SVM_H = np.diag([1.0, 1.0, 1.0, 1e-12])
_SVM_F = np.zeros(4)
_SVM_SOLVER = DaqpSolver()  # daqp's default settings
_PROX_SOLVER = DaqpSolver(eps_prox=-1.0)  # automatic proximal regularisation: the Hessian is singular


def max_margin_normal(points: FloatArray, verts: FloatArray) -> FloatArray | None:
    """Unit normal of the maximum-margin plane, pointing from `points` to `verts`.

    Hard-margin SVM: min |w|^2 s.t. w.p + c >= 1 (points), w.v + c <= -1 (verts),
    solved by daqp in centred, scaled coordinates. None if the hulls overlap.
    The caller recomputes the gap from the normal, so solver accuracy only
    affects room, never safety.
    """
    origin = points.mean(axis=0)
    scale = max(float(np.max(np.abs(np.concatenate([points, verts]) - origin))), 1e-12)
    p = (points - origin) / scale
    v = (verts - origin) / scale
    rows = np.concatenate(
        [
            np.concatenate([-p, -np.ones((p.shape[0], 1))], axis=1),
            np.concatenate([v, np.ones((v.shape[0], 1))], axis=1),
        ]
    )
    k = rows.shape[0]
    sense = np.zeros(k, dtype=np.int32)  # fresh each call: daqp writes its active set back
    sol = _SVM_SOLVER.solve(_SVM_H, _SVM_F, rows, -np.ones(k), np.full(k, -1e30), sense)
    if sol.status is QPStatus.INFEASIBLE:
        # a very thin gap makes the SVM badly scaled, and daqp may call it infeasible:
        # settle it with the closest-point pair, which is always well posed
        return _closest_pair_normal(p, v)
    w = np.asarray(sol.x[:3], dtype=float)
    norm = float(np.linalg.norm(w))
    if not sol.ok or not np.isfinite(norm) or norm == 0.0:
        return _fallback_normal(points, verts)
    return -w / norm


def _closest_pair_normal(points: FloatArray, verts: FloatArray) -> FloatArray | None:
    """Direction of the closest pair between two hulls; None when they touch or overlap.

    min |P^T l - V^T u|^2 over the two simplices (l, u >= 0, sum 1 each), with
    daqp's proximal regularisation for the singular Hessian. Safety never rests on
    its accuracy: callers recompute the gap from the returned normal.
    """
    na, nb = points.shape[0], verts.shape[0]
    m = np.concatenate([points, -verts]).T  # (3, na+nb)
    h = m.T @ m
    f = np.zeros(na + nb)
    eq = np.zeros((2, na + nb))
    eq[0, :na] = 1.0
    eq[1, na:] = 1.0
    n = na + nb
    upper = np.concatenate([np.full(n, 1.0), np.ones(2)])
    lower = np.concatenate([np.zeros(n), np.ones(2)])
    sense = np.concatenate([np.zeros(n, dtype=np.int32), np.full(2, SENSE_EQUALITY, dtype=np.int32)])
    sol = _PROX_SOLVER.solve(h, f, eq, upper, lower, sense)
    if not sol.ok:
        return None
    d = np.asarray(m @ np.asarray(sol.x, dtype=float), dtype=float)  # p* - v*
    norm = float(np.linalg.norm(d))
    if norm <= 1e-12:
        return None
    normal = -d / norm
    return normal if _gap(normal, points, verts) > 0.0 else None


def _fallback_normal(points: FloatArray, verts: FloatArray) -> FloatArray | None:
    """Centroid direction: always a valid direction, just not the roomiest."""
    d = verts.mean(axis=0) - points.mean(axis=0)
    norm = float(np.linalg.norm(d))
    return None if norm == 0.0 else d / norm


def _gap(normal: FloatArray, points: FloatArray, verts: FloatArray) -> float:
    return float(np.min(verts @ normal) - np.max(points @ normal))


def separation(points: FloatArray, verts: FloatArray) -> tuple[FloatArray | None, float]:
    """(normal, gap): the maximum-margin direction and the width of the empty slab.

    gap equals the distance between the two convex hulls when they are
    disjoint; (None, 0.0) when they overlap.
    """
    normal = max_margin_normal(points, verts)
    if normal is None:
        return None, 0.0
    return normal, _gap(normal, points, verts)


# --- batched segment / polytope separation ----------------------------------------
#
# For two disjoint convex sets the hard-margin SVM normal is the direction of their
# closest pair, and the margin is their distance. Between a segment and a polytope the
# closest pair is found among a few feature pairs (segment vs edge or vertex, endpoint
# vs facet), each a closed-form expression, so many segments against one obstacle are
# a handful of array operations instead of one QP each. Every candidate is a pair of
# points of the two sets, so a missed candidate could only cost room; the caller
# recomputes the gap from the normal, which is what safety rests on.


def _polytope_edges(verts: FloatArray, A: FloatArray, b: FloatArray) -> IntArray:
    """(E, 2) vertex index pairs spanning the edges (a vertex on none alone, as (i, i)).

    Two vertices on two common planes span a face of dimension <= 1, i.e. an edge;
    a redundant plane can only add a chord, which is inside the polytope (harmless).
    """
    tol = 1e-7 * max(1.0, float(np.max(np.abs(verts))))
    tight = (np.abs(verts @ A.T - b) <= tol).astype(np.intp)  # (V, F)
    shared = tight @ tight.T
    i, j = np.nonzero(np.triu(shared >= 2, 1))
    covered = np.zeros(verts.shape[0], dtype=bool)
    covered[i] = covered[j] = True
    lonely = np.flatnonzero(~covered)
    return np.concatenate([np.stack([i, j], axis=1), np.stack([lonely, lonely], axis=1)]).astype(np.intp)


def _dot(x: FloatArray, y: FloatArray) -> FloatArray:
    return np.asarray(np.sum(x * y, axis=-1))


def _segment_pairs(p: FloatArray, d1: FloatArray, q: FloatArray, d2: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Closest points of segments p + s d1 to segments q + t d2 (any shapes that broadcast, last
    axis 3): e.g. (s, 1, 3) against (1, E, 3) for every pair, or (P, 1, 3) against (P, E, 3).

    Ericson, Real-Time Collision Detection, 5.1.9, with the degenerate cases (a
    point for a segment, parallel segments) as array masks. Returns the two points
    of each pair, each of the broadcast shape.
    """
    a = _dot(d1, d1)
    e = _dot(d2, d2)
    c = _dot(d1, p - q)
    f = _dot(d2, p - q)
    bb = _dot(d1, d2)
    tiny = 1e-300
    a_ok, e_ok = a > tiny, e > tiny
    safe_a, safe_e = np.where(a_ok, a, 1.0), np.where(e_ok, e, 1.0)
    denom = a * e - bb * bb
    general = denom > tiny
    s = np.where(general, np.clip((bb * f - c * e) / np.where(general, denom, 1.0), 0.0, 1.0), 0.0)
    t = (bb * s + f) / safe_e
    s = np.where(t < 0.0, np.clip(-c / safe_a, 0.0, 1.0), np.where(t > 1.0, np.clip((bb - c) / safe_a, 0.0, 1.0), s))
    t = np.clip(t, 0.0, 1.0)
    # degenerate segments: a point against a segment (or a point)
    s = np.where(a_ok, np.where(e_ok, s, np.clip(-c / safe_a, 0.0, 1.0)), 0.0)
    t = np.where(e_ok, np.where(a_ok, t, np.clip(f / safe_e, 0.0, 1.0)), 0.0)
    return p + s[..., None] * d1, q + t[..., None] * d2


@dataclass(frozen=True)
class _Shapes:
    """Obstacles as padded arrays, one row each: vertices (n, V, 3), edges as start and
    direction (n, E, 3), unit-row planes (n, F, 3) and (n, F) with their Gram matrices
    (n, F, F). Short rows repeat their first entry, which changes no min, max or argmin."""

    verts: FloatArray
    edge0: FloatArray
    edged: FloatArray
    A: FloatArray
    b: FloatArray
    AA: FloatArray
    tol: FloatArray  # (n,) the foot-on-facet tolerance, relative to the obstacle's size


def _pad_rows(x: NDArray[Any], width: int) -> NDArray[Any]:
    idx = np.arange(width)
    return x[np.where(idx < x.shape[0], idx, 0)]


def _shapes(verts: Sequence[FloatArray], edges: Sequence[IntArray], planes: Sequence[tuple[FloatArray, FloatArray]]) -> _Shapes:
    V = max(v.shape[0] for v in verts)
    E = max(e.shape[0] for e in edges)
    F = max(p[0].shape[0] for p in planes)
    pv = np.stack([v if v.shape[0] == V else _pad_rows(v, V) for v in verts])
    if all(e is edges[0] for e in edges):  # all boxes: one edge list
        pe = np.broadcast_to(edges[0], (len(edges), *edges[0].shape))
    else:
        pe = np.stack([_pad_rows(e, E) for e in edges])
    rows = np.arange(len(verts))[:, None]
    e0, e1 = pv[rows, pe[:, :, 0]], pv[rows, pe[:, :, 1]]
    pA = np.stack([p[0] if p[0].shape[0] == F else _pad_rows(p[0], F) for p in planes])
    pb = np.stack([p[1] if p[1].shape[0] == F else _pad_rows(p[1], F) for p in planes])
    tol = 1e-12 * np.maximum(1.0, np.max(np.abs(pv), axis=(1, 2)))
    return _Shapes(pv, e0, e1 - e0, pA, pb, np.einsum("nfd,ngd->nfg", pA, pA), tol)


def _separations_padded(p0: FloatArray, p1: FloatArray, sh: _Shapes, ks: IntArray | None) -> tuple[FloatArray, FloatArray]:
    """`separations` of segment i (p0[i], p1[i]) against obstacle ks[i] of `sh`, every i at
    once (ks None: `sh` holds one obstacle, against every segment)."""
    s = p0.shape[0]
    normals = np.full((s, 3), np.nan)
    gaps = np.zeros(s)
    if s == 0:
        return normals, gaps
    if ks is None:
        verts, e0, ed, A, b, AA, tol = sh.verts, sh.edge0, sh.edged, sh.A, sh.b, sh.AA, sh.tol
    else:
        verts, e0, ed, A, b = sh.verts[ks], sh.edge0[ks], sh.edged[ks], sh.A[ks], sh.b[ks]
        AA, tol = sh.AA[ks], sh.tol[ks]
    d1 = p1 - p0
    # the segment against every edge (and lone vertex): (s, E)
    x_seg, x_obs = _segment_pairs(p0[:, None, :], d1[:, None, :], e0, ed)
    dist = np.linalg.norm(x_obs - x_seg, axis=-1)
    # each end against each facet it faces, where its foot lands on the facet: (s, 2F);
    # A . foot = A . end - height (A a_f), so the feet themselves are not needed yet
    ends = np.stack([p0, p1], axis=1)  # (s, 2, 3)
    proj = np.matmul(ends, np.swapaxes(A, -1, -2))  # (s, 2, F)
    bq = np.broadcast_to(b, (s, b.shape[-1]))
    height = proj - bq[:, None, :]
    lim = (bq + np.broadcast_to(tol, (s,))[:, None])[:, None, None, :]
    on = (height > 0.0) & np.all(proj[:, :, None, :] - height[..., None] * np.broadcast_to(AA, (s, *AA.shape[-2:]))[:, None] <= lim, axis=-1)
    best = np.argmin(np.concatenate([dist, np.where(on, height, np.inf).reshape(s, -1)], axis=1), axis=1)
    n_e, n_f = dist.shape[1], height.shape[2]
    rows = np.arange(s)
    by_edge = best < n_e
    which = np.where(by_edge, 0, best - n_e)
    end, facet = which // n_f, which % n_f
    foot_end = ends[rows, end]
    e_best = np.minimum(best, n_e - 1)
    seg_pt = np.where(by_edge[:, None], x_seg[rows, e_best], foot_end)
    A_f = np.broadcast_to(A, (s, *A.shape[-2:]))[rows, facet]
    obs_pt = np.where(by_edge[:, None], x_obs[rows, e_best], foot_end - height[rows, end, facet][:, None] * A_f)
    diff = obs_pt - seg_pt
    norm = np.linalg.norm(diff, axis=1)
    n = diff / np.where(norm > 0.0, norm, 1.0)[:, None]
    vmin = np.min(np.einsum("sd,svd->sv", n, np.broadcast_to(verts, (s, *verts.shape[-2:]))), axis=1)
    gap = vmin - np.maximum(np.sum(n * p0, axis=1), np.sum(n * p1, axis=1))
    # disjoint sets: the closest pair's direction leaves a slab as wide as their distance;
    # no direction leaves a positive one when they meet (a crossing segment lands here)
    apart = (norm > 0.0) & (gap > 0.0)
    normals[apart] = n[apart]
    gaps[apart] = gap[apart]
    return normals, gaps


def separations(
    p0: FloatArray, p1: FloatArray, verts: FloatArray, A: FloatArray, b: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Max-margin normals and gaps between many segments and one obstacle.

    p0, p1 (s, 3) segment ends; the obstacle by its vertices and unit-row planes.
    Returns normals (s, 3) pointing from segment to obstacle (NaN rows where they
    meet) and gaps (s,) = min_v a.v - max_p a.p (0 where they meet), as
    `separation` would for each segment, but exact up to rounding (no QP).
    """
    sh = _shapes([verts], [_polytope_edges(verts, A, b)], [(A, b)])
    one = _Shapes(sh.verts[0], sh.edge0[0], sh.edged[0], sh.A[0], sh.b[0], sh.AA[0], sh.tol[0])
    return _separations_padded(p0, p1, one, None)


# --- obstacle set -----------------------------------------------------------------


@dataclass(frozen=True)
class _Obstacles:
    """All obstacles' vertices stacked, with offsets, bounding spheres and boxes, and padded."""

    verts: tuple[FloatArray, ...]
    stacked: FloatArray  # (N, 3)
    starts: IntArray  # (n,) first row of each obstacle in `stacked`
    centres: FloatArray  # (n, 3)
    radii: FloatArray  # (n,)
    planes: tuple[tuple[FloatArray, FloatArray], ...]
    lo: FloatArray  # (n, 3) bounding boxes of the vertices
    hi: FloatArray
    shapes: _Shapes | None  # None without obstacles

    @property
    def n(self) -> int:
        return len(self.verts)

    def margins(self, A: FloatArray, b: FloatArray) -> FloatArray:
        """(n, P) min signed distance of each obstacle's vertices beyond each plane."""
        if self.n == 0 or A.shape[0] == 0:
            return np.full((self.n, A.shape[0]), -np.inf)
        s = self.stacked @ A.T - b
        return np.minimum.reduceat(s, self.starts, axis=0)


def _prepare_obstacles(obstacles: Sequence[Polytope], first_index: int = 0) -> _Obstacles:
    """Checks every obstacle (naming the first bad one) and gathers the arrays the builders use.

    Axis-aligned boxes, the common case, are recognised in one vectorised pass (their
    corners and edges are known); any other polytope goes through `polytope_vertices`.
    """
    n = len(obstacles)
    for i, obs in enumerate(obstacles):
        if not isinstance(obs, Polytope):
            raise ValueError(f"obstacles[{first_index + i}]: expected a Polytope, got {type(obs).__name__}")
    if n == 0:
        empty = np.zeros((0, 3))
        return _Obstacles((), empty, np.zeros(0, dtype=np.intp), empty, np.zeros(0), (), empty, empty, None)
    verts: list[FloatArray | None] = [None] * n
    planes: list[tuple[FloatArray, FloatArray] | None] = [None] * n
    edges: list[IntArray | None] = [None] * n
    six = [i for i, o in enumerate(obstacles) if np.shape(o.A) == (6, 3) and np.shape(o.b) == (6,)]
    if six:
        A6 = np.array([obstacles[i].A for i in six], dtype=float)
        b6 = np.array([obstacles[i].b for i in six], dtype=float)
        norms = np.linalg.norm(A6, axis=2)
        fine = np.all(np.isfinite(A6), axis=(1, 2)) & np.all(np.isfinite(b6), axis=1) & np.all(norms > 1e-12, axis=1)
        safe = np.where(fine[:, None], norms, 1.0)
        An, bn = A6 / safe[..., None], b6 / safe
        is_box, lo, hi = _box_extents(An, bn)
        is_box &= fine
        corners = _box_corners(lo, hi)
        if len(six) == n and bool(np.all(is_box)):
            return _boxes(corners, An, bn, lo, hi)
        for row in np.flatnonzero(is_box).tolist():
            i = six[row]
            verts[i] = corners[row]
            planes[i] = (An[row], bn[row])
            edges[i] = _BOX_EDGES
    for i, obs in enumerate(obstacles):
        if verts[i] is not None:
            continue
        name = f"obstacles[{first_index + i}]"
        A, b = normalised(obs, name)
        v = polytope_vertices(obs, name)
        verts[i], planes[i], edges[i] = v, (A, b), _polytope_edges(v, A, b)
    vs = [v for v in verts if v is not None]
    ps = [p for p in planes if p is not None]
    es = [e for e in edges if e is not None]
    counts = np.array([v.shape[0] for v in vs])
    centres = np.stack([v.mean(axis=0) for v in vs])
    stacked = np.concatenate(vs)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.intp)
    owner = np.repeat(np.arange(n), counts)
    radii = np.zeros(n)
    np.maximum.at(radii, owner, np.linalg.norm(stacked - centres[owner], axis=1))
    lo = np.minimum.reduceat(stacked, starts, axis=0)
    hi = np.maximum.reduceat(stacked, starts, axis=0)
    return _Obstacles(tuple(vs), stacked, starts, centres, radii, tuple(ps), lo, hi, _shapes(vs, es, ps))


def _boxes(corners: FloatArray, A: FloatArray, b: FloatArray, lo: FloatArray, hi: FloatArray) -> _Obstacles:
    """`_prepare_obstacles` when every obstacle is an axis-aligned box: all in array operations."""
    n = corners.shape[0]
    e = _BOX_EDGES
    e0 = corners[:, e[:, 0]]
    shapes = _Shapes(corners, e0, corners[:, e[:, 1]] - e0, A, b, np.einsum("nfd,ngd->nfg", A, A),
                     1e-12 * np.maximum(1.0, np.max(np.abs(corners), axis=(1, 2))))
    radii = 0.5 * np.linalg.norm(hi - lo, axis=1)
    return _Obstacles(tuple(corners), corners.reshape(-1, 3), np.arange(n, dtype=np.intp) * 8, 0.5 * (lo + hi),
                      radii, tuple(zip(A, b, strict=True)), lo, hi, shapes)


def _segment_point_distance(p0: FloatArray, p1: FloatArray, c: FloatArray) -> FloatArray:
    """(s, n) distance from segments [p0_s, p1_s] to points c_n."""
    return _pair_point_distance(p0[:, None, :], p1[:, None, :], c[None, :, :])


def _pair_point_distance(p0: FloatArray, p1: FloatArray, c: FloatArray) -> FloatArray:
    """Distance from segments [p0, p1] to points c, elementwise over broadcast leading axes."""
    d = p1 - p0
    dd = _dot(d, d)
    t = np.clip(_dot(c - p0, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
    return np.asarray(np.linalg.norm(c - (p0 + t[..., None] * d), axis=-1))


# --- map box ------------------------------------------------------------------------


def _map_planes(map_box: tuple[ArrayLike, ArrayLike] | None, radius: float) -> tuple[FloatArray, FloatArray]:
    if map_box is None:
        return np.zeros((0, 3)), np.zeros(0)
    lo = _as_point(map_box[0], "map_box.min")
    hi = _as_point(map_box[1], "map_box.max")
    if np.any(hi - lo <= 2.0 * radius):
        axis = int(np.argmax(hi - lo <= 2.0 * radius))
        raise ValueError(
            f"map_box: extent {hi[axis] - lo[axis]:g} along axis {axis} leaves no room "
            f"for a vehicle of radius {radius:g}"
        )
    eye = np.eye(3)
    return np.concatenate([eye, -eye]), np.concatenate([hi - radius, -(lo + radius)])


def _analysis_box(waypoints: FloatArray, obs: _Obstacles) -> tuple[FloatArray, FloatArray]:
    """A box enclosing every waypoint and obstacle with room to spare.

    Without a map box a corridor may be unbounded; facets are then judged
    inside this box. A plane that only matters outside it bounds a region with
    no obstacle, so dropping it keeps every obstacle excluded.
    """
    pts = np.concatenate([waypoints, obs.stacked])
    lo, hi = pts.min(axis=0), pts.max(axis=0)
    pad = 1.0 + float(np.max(hi - lo))
    eye = np.eye(3)
    return np.concatenate([eye, -eye]), np.concatenate([hi + pad, -(lo - pad)])


# --- pruning ----------------------------------------------------------------------------


def _facet_mask(A: FloatArray, b: FloatArray, verts: FloatArray) -> BoolArray:
    """Planes of {A x <= b} that carry a 2-D face (the non-redundant ones)."""
    tol = 1e-8 * max(1.0, float(np.max(np.abs(b))))
    on = np.abs(verts @ A.T - b) <= tol  # (V, P)
    mask = np.zeros(A.shape[0], dtype=bool)
    for p in np.flatnonzero(on.sum(axis=0) >= 3):
        face = verts[on[:, p]]
        sv = np.linalg.svd(face - face.mean(axis=0), compute_uv=False)
        mask[p] = sv[1] > tol
    return mask


def _first_of_duplicates(A: FloatArray, b: FloatArray) -> BoolArray:
    """Drop planes parallel to a tighter (or identical earlier) one."""
    tol = 1e-9 * max(1.0, float(np.max(np.abs(b)))) if b.size else 0.0
    same = (A @ A.T) >= 1.0 - 1e-12
    idx = np.arange(A.shape[0])
    tighter = b[None, :] < b[:, None] - tol
    equal_earlier = (np.abs(b[None, :] - b[:, None]) <= tol) & (idx[None, :] < idx[:, None])
    return np.asarray(~np.any(same & (tighter | equal_earlier), axis=1), dtype=bool)


def _prune(
    A: FloatArray,
    b: FloatArray,
    certs: FloatArray,
    radius: float,
    aux: tuple[FloatArray, FloatArray] | None,
) -> IntArray:
    """Indices of the planes to keep: the facets, plus whatever restores certificates.

    certs (n_obstacles, P) holds each obstacle's margin beyond each plane.
    """
    keep = _first_of_duplicates(A, b)
    idx = np.flatnonzero(keep)
    Ak, bk = A[idx], b[idx]
    if aux is not None:
        Ak, bk = np.concatenate([Ak, aux[0]]), np.concatenate([bk, aux[1]])
    verts = _vertices(Ak, bk)
    if verts.shape[0] < 4:
        return idx  # numerically flat or empty: keeping planes is always safe
    facets = _facet_mask(Ak, bk, verts)[: idx.shape[0]]
    chosen = set(idx[facets].tolist())
    certifies = certs >= radius - CERT_TOL  # (n, P)
    certifies[:, ~keep] = False  # prefer survivors: a dropped duplicate has a kept twin
    chosen_mask = np.zeros(A.shape[0], dtype=bool)
    chosen_mask[list(chosen)] = True
    missing = ~np.any(certifies[:, chosen_mask], axis=1) & np.any(certifies, axis=1)
    while np.any(missing):
        # Greedy: the plane that restores the most certificates.
        p = int(np.argmax(certifies[missing].sum(axis=0)))
        chosen_mask[p] = True
        missing &= ~certifies[:, p]
    return np.flatnonzero(chosen_mask)


# --- building ----------------------------------------------------------------------------


@dataclass(frozen=True)
class _Context:
    waypoints: FloatArray
    obs: _Obstacles
    radius: float
    map_A: FloatArray
    map_b: FloatArray
    aux: tuple[FloatArray, FloatArray] | None
    first_index: int  # index of obs[0] in the caller's numbering


def _validate_waypoints(waypoints: ArrayLike) -> FloatArray:
    wps = _as_points(waypoints, "waypoints")
    if wps.shape[0] < 2:
        raise ValueError(f"waypoints: need at least 2, got {wps.shape[0]}")
    return wps


def _validate_radius(radius: float) -> float:
    r = float(radius)
    if not np.isfinite(r) or r < 0.0:
        raise ValueError(f"radius: must be finite and >= 0, got {radius}")
    return r


def _check_waypoints_in_map(ctx: _Context) -> None:
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


def _point_distance(point: FloatArray, ctx: _Context, k: int) -> float:
    """Distance from a point to obstacle k (0 if inside)."""
    normal, gap = separation(point[None, :], ctx.obs.verts[k])
    return 0.0 if normal is None else max(gap, 0.0)


def _check_waypoints_clear(ctx: _Context, pairs: tuple[IntArray, IntArray] | None = None) -> None:
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


def _blocked(ctx: _Context, j: int, k: int, gap: float) -> CorridorError:
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


def _separation_arrays(ctx: _Context, js: IntArray, ks: IntArray) -> tuple[FloatArray, FloatArray]:
    """Max-margin normals (p, 3; NaN where they meet) and gaps (p,) of the pairs
    (segment js[i], obstacle ks[i]), all in one batch."""
    if js.shape[0] == 0 or ctx.obs.shapes is None:
        return np.full((js.shape[0], 3), np.nan), np.zeros(js.shape[0])
    sh = ctx.obs.shapes
    step = max(1, _PAIR_BATCH // (sh.A.shape[1] ** 2 + sh.edge0.shape[1] + sh.verts.shape[1]))
    parts = [
        _separations_padded(ctx.waypoints[js[i : i + step]], ctx.waypoints[js[i : i + step] + 1], sh, ks[i : i + step])
        for i in range(0, js.shape[0], step)
    ]
    return np.concatenate([p[0] for p in parts]), np.concatenate([p[1] for p in parts])


def _separations(ctx: _Context, js: IntArray, ks: IntArray) -> dict[tuple[int, int], Separation]:
    normals, gaps = _separation_arrays(ctx, js, ks)
    return {
        (j, k): (None if np.isnan(n[0]) else n, g)
        for j, k, n, g in zip(js.tolist(), ks.tolist(), normals, gaps.tolist(), strict=True)
    }


def _obstacle_plane(ctx: _Context, j: int, k: int, sep: Separation | None = None) -> tuple[FloatArray, float]:
    """The roomiest safe plane (unit a, offset) between segment j and obstacle k."""
    verts = ctx.obs.verts[k]
    if sep is None:
        sep = _separations(ctx, np.array([j]), np.array([k]))[(j, k)]
    normal, gap = sep
    if normal is None or gap < 2.0 * ctx.radius:
        raise _blocked(ctx, j, k, gap)
    return normal, float(np.min(verts @ normal)) - ctx.radius


def _add_planes(
    ctx: _Context,
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


def _finish(ctx: _Context, A: FloatArray, b: FloatArray) -> Polytope:
    keep = _prune(A, b, ctx.obs.margins(A, b), ctx.radius, ctx.aux)
    return Polytope(A=np.ascontiguousarray(A[keep]), b=np.ascontiguousarray(b[keep]))


def _context(
    wps: FloatArray,
    obs: _Obstacles,
    map_box: tuple[ArrayLike, ArrayLike] | None,
    radius: float,
    first_index: int = 0,
    all_obs: _Obstacles | None = None,
) -> _Context:
    map_A, map_b = _map_planes(map_box, radius)
    aux = None if map_box is not None else _analysis_box(wps, all_obs if all_obs is not None else obs)
    return _Context(wps, obs, radius, map_A, map_b, aux, first_index)


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
    wps = _validate_waypoints(waypoints)
    r = _validate_radius(radius)
    if influence is not None and not (np.isfinite(influence) and influence >= 0.0):
        raise ValueError(f"influence: must be finite and >= 0, got {influence}")
    obs = _prepare_obstacles(obstacles)
    map_A, map_b = _map_planes(map_box, r)
    ctx = _Context(wps, obs, r, map_A, map_b, None, 0)
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
    _check_waypoints_clear(ctx, (key // max(obs.n, 1), key % max(obs.n, 1)))
    lower = np.maximum(_pair_point_distance(p0[js], p1[js], obs.centres[ks]) - obs.radii[ks], 0.0)
    order = np.lexsort((ks, lower, js))  # by segment, nearest first (as the sequential rule)
    js, ks = js[order], ks[order]
    normals, gaps = _separation_arrays(ctx, js, ks)
    bad = np.isnan(normals[:, 0]) | (gaps < 2.0 * r)
    if np.any(bad):
        i = int(np.argmax(bad))
        raise _blocked(ctx, int(js[i]), int(ks[i]), float(gaps[i]))
    offsets = _min_over_vertices(obs, normals, ks) - r
    return _assemble(obs, r, flo, fhi, js, ks, normals, offsets)


_MIN_PAD = 0.5  # metres: the analysis box never hugs the segment closer than 2 r + this
_FRAME_A = np.concatenate([np.eye(3), -np.eye(3)])


def analysis_boxes(
    p0: FloatArray, p1: FloatArray, pad: FloatArray, map_box: tuple[ArrayLike, ArrayLike] | None, radius: float
) -> tuple[FloatArray, FloatArray]:
    """(lo, hi) (s, 3) of each segment's analysis box: its bounding box padded by pad (s,),
    clipped to the map box shrunk by radius. Its six faces are the first six planes of
    the segment's corridor, before pruning."""
    lo = np.minimum(p0, p1) - pad[:, None]
    hi = np.maximum(p0, p1) + pad[:, None]
    if map_box is not None:
        _, map_b = _map_planes(map_box, radius)
        hi = np.minimum(hi, map_b[:3])
        lo = np.maximum(lo, -map_b[3:])
    return lo, hi


def _assemble(
    obs: _Obstacles,
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
            cert = _mutual_certificates(obs.shapes.verts[ks[pidx]], normals[pidx], offsets[pidx], r)
            added = _greedy_planes(cert)
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
            A = np.concatenate([np.broadcast_to(_FRAME_A, (G, 6, 3)), normals[rows]], axis=1)
            b = np.concatenate([fb[segs], offsets[rows]], axis=1)
            distinct = _first_of_duplicates_padded(A, b, np.ones((G, 6 + Q), dtype=bool))
            keep = distinct & facet_masks(A, b)
            keep[:, :6] |= far[segs]
            if Q:
                _restore_certificates(keep[:, 6:], distinct[:, 6:], [certs[j] for j in segs.tolist()])
            for g, j in enumerate(segs.tolist()):
                out[j] = Polytope(A=np.ascontiguousarray(A[g, keep[g]]), b=np.ascontiguousarray(b[g, keep[g]]))
    return tuple(p for p in out if p is not None)


def _mutual_certificates(verts: FloatArray, normals: FloatArray, offsets: FloatArray, r: float) -> BoolArray:
    """(G, K, K): candidate c (verts (G, K, V, 3)) is kept r away by candidate d's plane."""
    G, K, V, _ = verts.shape
    proj = np.matmul(verts.reshape(G, K * V, 3), normals.transpose(0, 2, 1)).reshape(G, K, V, K)
    return np.asarray(np.min(proj, axis=2) - offsets[:, None, :] >= r - CERT_TOL)


def _greedy_planes(cert: BoolArray) -> BoolArray:
    """(G, K): the candidates (nearest first) that get a plane: those no earlier plane certifies."""
    G, K, _ = cert.shape
    added = np.zeros((G, K), dtype=bool)
    certified = np.zeros((G, K), dtype=bool)
    for i in range(K):
        need = np.flatnonzero(~certified[:, i])
        added[need, i] = True
        certified[need] |= cert[need, :, i]
    return added


def _restore_certificates(keep: BoolArray, distinct: BoolArray, certs: list[BoolArray]) -> None:
    """Where pruning left a candidate without a plane that keeps it r away, keep planes again,
    greedily the one restoring the most (as `_prune`). keep, distinct: (G, Q) over the
    corridors' obstacle planes, updated in place; certs[g] (K_g, Q): which plane certifies
    which candidate."""
    G, Q = keep.shape
    width = max(c.shape[0] for c in certs)
    cert = np.zeros((G, width, Q), dtype=bool)
    for g, c in enumerate(certs):
        cert[g, : c.shape[0]] = c
    cert &= distinct[:, None, :]  # a dropped duplicate has a kept twin
    missing = ~np.any(cert & keep[:, None, :], axis=2) & np.any(cert, axis=2)
    for g in np.flatnonzero(np.any(missing, axis=1)).tolist():
        miss, cg = missing[g], cert[g]
        while np.any(miss):
            p = int(np.argmax(cg[miss].sum(axis=0)))
            keep[g, p] = True
            miss &= ~cg[:, p]


def update_corridors(
    waypoints: ArrayLike,
    corridors: Sequence[Polytope],
    obstacles: Sequence[Polytope],
    new_obstacles: Sequence[Polytope],
    map_box: tuple[ArrayLike, ArrayLike] | None,
    radius: float,
    *,
    prune: bool = True,
) -> tuple[tuple[Polytope, ...], list[int]]:
    """Add pop-up obstacles to existing corridors, touching affected segments only.

    A segment is affected when no plane of its corridor already keeps a new
    obstacle radius away (the certificate test: conservative, it may rebuild a
    corridor that merely comes close, never skips one that overlaps). Affected
    corridors get a maximum-margin plane per uncertified new obstacle and are
    pruned again; the others are returned as the very same objects. New
    obstacles are numbered after `obstacles` in errors.

    prune=False (the in-flight fast path): affected corridors only get the new
    planes appended, plus the cheap removal of parallel looser duplicates. The
    region, containment and every certificate are exactly those of the pruned
    result; planes that stopped being facets are kept (a few redundant QP rows),
    which skips the vertex enumeration (~2 ms a corridor) and the preparation
    of the old obstacles, which then are only counted. It runs over all
    affected corridors at once (same planes, order and errors as one corridor
    at a time): a pop-up on map-box-only corridors affects every one of them.
    """
    wps = _validate_waypoints(waypoints)
    r = _validate_radius(radius)
    if len(corridors) != wps.shape[0] - 1:
        raise ValueError(f"corridors: expected {wps.shape[0] - 1} (one per segment), got {len(corridors)}")
    new = _prepare_obstacles(new_obstacles, first_index=len(obstacles))
    if prune:
        everyone = _prepare_obstacles([*obstacles, *new_obstacles])
        ctx = _context(wps, new, map_box, r, first_index=len(obstacles), all_obs=everyone)
        full = _Context(wps, everyone, r, ctx.map_A, ctx.map_b, ctx.aux, 0)
    else:
        ctx = _context(wps, new, None, r, first_index=len(obstacles))
    _check_waypoints_clear(ctx)
    A_all, b_all, starts = _stack_corridors(corridors)
    out = list(corridors)
    changed: list[int] = []
    if new.n == 0:
        return tuple(out), changed
    certified = _certified_by_corridors(new, A_all, b_all, starts, r)  # (n_new, corridors)
    affected = np.flatnonzero(~np.all(certified, axis=0))
    if affected.size == 0:
        return tuple(out), changed
    lower = np.maximum(_segment_point_distance(wps[:-1], wps[1:], new.centres) - new.radii, 0.0)
    # the uncertified (segment, new obstacle) pairs need a plane, unless an earlier new plane of
    # the same corridor certifies them: their separations, batched per obstacle
    ks, js = np.nonzero(~certified[:, affected])
    if not prune:
        polys = _append_planes(ctx, affected, A_all, b_all, starts, certified, lower, (js, ks))
        for j, poly in zip(affected.tolist(), polys, strict=True):
            out[j] = poly
        return tuple(out), affected.tolist()
    seps = _separations(ctx, affected[js], ks)
    for j in affected.tolist():
        A, b = A_all[starts[j] : starts[j + 1]], b_all[starts[j] : starts[j + 1]]
        order = np.argsort(lower[j], kind="stable")
        A2, b2 = _add_planes(ctx, j, A, b, order, np.zeros(new.n, dtype=bool), seps)
        out[j] = _finish(full, A2, b2)
        changed.append(j)
    return tuple(out), changed


def _stack_corridors(corridors: Sequence[Polytope]) -> tuple[FloatArray, FloatArray, IntArray]:
    """Every corridor's unit rows stacked, and where each corridor starts (len + 1 offsets).

    Checks as `normalised` does, naming the first bad corridor, without a Python pass
    of array operations per corridor (a long mission has a thousand of them).
    """
    As = [np.asarray(c.A, dtype=float) for c in corridors]
    bs = [np.asarray(c.b, dtype=float) for c in corridors]
    for j, (A, b) in enumerate(zip(As, bs, strict=True)):
        if A.ndim != 2 or A.shape[1] != 3 or b.shape != (A.shape[0],):
            normalised(corridors[j], f"corridors[{j}]")  # raises, with the reason
    counts = np.array([A.shape[0] for A in As], dtype=np.intp)
    starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.intp)
    A_all = np.concatenate(As) if As else np.zeros((0, 3))
    b_all = np.concatenate(bs) if bs else np.zeros(0)
    norms = np.linalg.norm(A_all, axis=1)
    bad = ~(np.all(np.isfinite(A_all), axis=1) & np.isfinite(b_all)) | (norms <= 1e-12)
    if np.any(bad):
        j = int(np.searchsorted(starts, int(np.argmax(bad)), side="right") - 1)
        normalised(corridors[j], f"corridors[{j}]")  # raises, with the reason
    return A_all / norms[:, None], b_all / norms, starts


def _certified_by_corridors(
    obs: _Obstacles, A_all: FloatArray, b_all: FloatArray, starts: IntArray, radius: float
) -> BoolArray:
    """(n, corridors): some plane of the corridor keeps obstacle k radius away."""
    n_cor = starts.shape[0] - 1
    out = np.zeros((obs.n, n_cor), dtype=bool)
    rows = obs.margins(A_all, b_all) >= radius - CERT_TOL  # (n, R)
    nonempty = np.flatnonzero(starts[1:] > starts[:-1])
    if nonempty.size:
        out[:, nonempty] = np.logical_or.reduceat(rows, starts[nonempty], axis=1)
    return out


def _append_planes(
    ctx: _Context,
    affected: IntArray,
    A_all: FloatArray,
    b_all: FloatArray,
    starts: IntArray,
    certified: BoolArray,
    lower: FloatArray,
    pairs: tuple[IntArray, IntArray],
) -> list[Polytope]:
    """The unpruned update of every affected corridor at once: `_add_planes` (nearest new
    obstacle first, a plane for each one still uncertified) then `_first_of_duplicates`,
    as array operations over corridors; the only Python loop is over new obstacles.

    pairs: (rows into `affected`, obstacles) of the uncertified pairs, whose separations
    are computed here in one batch per obstacle; a plane is only ever needed for them.
    """
    obs, r = ctx.obs, ctx.radius
    n_aff, n_new = affected.shape[0], obs.n
    pa, pk = pairs
    normals, gaps = _separation_arrays(ctx, affected[pa], pk)
    pair_of = np.full((n_aff, n_new), -1, dtype=np.intp)
    pair_of[pa, pk] = np.arange(pa.shape[0])
    orders = np.argsort(lower[affected], axis=1, kind="stable")  # (n_aff, n_new), nearest first
    cert = certified[:, affected].T.copy()  # (n_aff, n_new)
    new_A = np.zeros((n_aff, n_new, 3))  # by round
    new_b = np.zeros((n_aff, n_new))
    added = np.zeros((n_aff, n_new), dtype=bool)
    blocked_at = np.full(n_aff, n_new, dtype=np.intp)  # first round whose plane does not exist
    every = np.arange(n_aff)
    for i in range(n_new):
        k = orders[:, i]
        need = np.flatnonzero(~cert[every, k] & (blocked_at == n_new))
        if need.size == 0:
            continue
        p = pair_of[need, k[need]]
        n, g = normals[p], gaps[p]
        bad = np.isnan(n[:, 0]) | (g < 2.0 * r)
        blocked_at[need[bad]] = i
        need, n, kk = need[~bad], n[~bad], k[need[~bad]]
        off = _min_over_vertices(obs, n, kk) - r
        new_A[need, i], new_b[need, i], added[need, i] = n, off, True
        cert[need] |= (obs.margins(n, off) >= r - CERT_TOL).T
    if np.any(blocked_at < n_new):
        a = int(np.argmax(blocked_at < n_new))
        k0 = int(orders[a, blocked_at[a]])
        raise _blocked(ctx, int(affected[a]), k0, float(gaps[pair_of[a, k0]]))
    A_pad, b_pad, valid = _padded_corridors(affected, A_all, b_all, starts, new_A, new_b, added)
    keep = _first_of_duplicates_padded(A_pad, b_pad, valid)
    return [
        Polytope(A=np.ascontiguousarray(A_pad[a, keep[a]]), b=np.ascontiguousarray(b_pad[a, keep[a]]))
        for a in range(n_aff)
    ]


def _min_over_vertices(obs: _Obstacles, normals: FloatArray, ks: IntArray) -> FloatArray:
    """min over obstacle ks[i]'s vertices of normals[i] . v, for every i."""
    if ks.shape[0] == 0 or obs.shapes is None:
        return np.zeros(ks.shape[0])
    return np.asarray(np.min(np.einsum("pd,pvd->pv", normals, obs.shapes.verts[ks]), axis=1))


def _padded_corridors(
    affected: IntArray,
    A_all: FloatArray,
    b_all: FloatArray,
    starts: IntArray,
    new_A: FloatArray,
    new_b: FloatArray,
    added: BoolArray,
) -> tuple[FloatArray, FloatArray, BoolArray]:
    """Each affected corridor's old rows then its added rows, padded: (n, K, 3), (n, K), valid."""
    n_aff = affected.shape[0]
    n_old = starts[affected + 1] - starts[affected]
    total = n_old + added.sum(axis=1)
    width = int(total.max()) if n_aff else 0
    A_pad = np.zeros((n_aff, width, 3))
    b_pad = np.zeros((n_aff, width))
    owner = np.repeat(np.arange(n_aff), n_old)
    pos = np.arange(owner.shape[0]) - np.repeat(np.cumsum(n_old) - n_old, n_old)
    src = starts[affected][owner] + pos
    A_pad[owner, pos], b_pad[owner, pos] = A_all[src], b_all[src]
    a, i = np.nonzero(added)
    slot = n_old[a] + np.cumsum(added, axis=1)[a, i] - 1
    A_pad[a, slot], b_pad[a, slot] = new_A[a, i], new_b[a, i]
    valid = np.arange(width)[None, :] < total[:, None]
    return A_pad, b_pad, valid


def _first_of_duplicates_padded(A: FloatArray, b: FloatArray, valid: BoolArray) -> BoolArray:
    """`_first_of_duplicates` of every padded corridor at once: (n, K) rows to keep."""
    bmax = np.max(np.where(valid, np.abs(b), 0.0), axis=1, initial=0.0)
    tol = (1e-9 * np.maximum(1.0, bmax))[:, None, None]
    same = (np.einsum("nkd,nld->nkl", A, A) >= 1.0 - 1e-12) & valid[:, None, :] & valid[:, :, None]
    idx = np.arange(A.shape[1])
    tighter = b[:, None, :] < b[:, :, None] - tol
    equal_earlier = (np.abs(b[:, None, :] - b[:, :, None]) <= tol) & (idx[None, :] < idx[:, None])[None]
    return np.asarray(valid & ~np.any(same & (tighter | equal_earlier), axis=2), dtype=bool)
