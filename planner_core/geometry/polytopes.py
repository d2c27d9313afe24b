"""Polytopes in both representations: vertex enumeration (H -> V, cached), convex hulls
(V -> H, a closed form for small point sets and boxes), and point/segment queries."""


from __future__ import annotations

from collections import OrderedDict
from itertools import combinations

import numpy as np
from numpy.typing import ArrayLike

from planner_core.facets import triples
from planner_core.geometry.common import BoolArray, IntArray
from planner_core.problem import FloatArray, Polytope

_DET_TOL = 1e-12  # unit normals: |det| below this means three planes share no single point
_CHUNK = 20000  # triples per vectorised batch (bounds memory for big hulls)
FRAME_A = np.concatenate([np.eye(3), -np.eye(3)])


# --- small geometry helpers -------------------------------------------------


def as_points(values: ArrayLike, name: str) -> FloatArray:
    pts = np.asarray(values, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 3:
        raise ValueError(f"{name}: expected shape (k, 3), got {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ValueError(f"{name}: contains non-finite values")
    return pts


def as_point(values: ArrayLike, name: str) -> FloatArray:
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


def enumerate_vertices(A: FloatArray, b: FloatArray) -> FloatArray:
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
BOX_EDGES = np.array([(c, c | (1 << a)) for c in range(8) for a in range(3) if not c & (1 << a)], dtype=np.intp)


def box_extents(A: FloatArray, b: FloatArray) -> tuple[BoolArray, FloatArray, FloatArray]:
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


def box_corners(lo: FloatArray, hi: FloatArray) -> FloatArray:
    """(n, 8, 3) corners of the boxes [lo, hi] (n, 3), numbered as `_CORNER_BITS`."""
    return np.where(_CORNER_BITS[None].astype(bool), hi[:, None, :], lo[:, None, :])


HULL_VERTICES = "_hull_vertices"  # a Polytope built from vertices carries them under this name
_VERTEX_CACHE: OrderedDict[tuple[tuple[int, ...], bytes, bytes], FloatArray] = OrderedDict()
_VERTEX_CACHE_SIZE = 256


def polytope_vertices(poly: Polytope, name: str = "polytope") -> FloatArray:
    """Vertices (k, 3) of a bounded, non-empty polytope; ValueError otherwise.

    Results are cached by the exact bytes of (A, b) (read-only arrays): a pop-up
    obstacle is checked when its message is parsed and again by the replan that
    avoids it, and the vertex enumeration is a millisecond or two each time.
    """
    given = getattr(poly, HULL_VERTICES, None)
    if given is not None:  # a hull's own vertices, wherever it was built (polytope_from_vertices)
        _remember_vertices(poly, given)
        return given  # type: ignore[no-any-return]
    A0 = np.ascontiguousarray(poly.A, dtype=float)
    b0 = np.ascontiguousarray(poly.b, dtype=float)
    key = (A0.shape, A0.tobytes(), b0.tobytes())
    hit = _VERTEX_CACHE.get(key)
    if hit is not None:
        return hit
    A, b = normalised(poly, name)
    if A.shape[0] == 6:
        is_box, lo, hi = box_extents(A[None], b[None])
        if is_box[0]:
            verts = np.ascontiguousarray(box_corners(lo, hi)[0])
            verts.flags.writeable = False
            _remember_vertices(poly, verts)
            return verts
    if not _is_bounded(A):
        raise ValueError(f"{name}: polytope is unbounded (its planes do not enclose a region)")
    verts = enumerate_vertices(A, b)
    if verts.shape[0] == 0:
        raise ValueError(f"{name}: polytope is empty (its planes have no common point)")
    verts.flags.writeable = False
    _remember_vertices(poly, verts)
    return verts


def clear_vertex_cache() -> None:
    """Forget every cached vertex set (benchmarks: a user's obstacles are new to the process)."""
    _VERTEX_CACHE.clear()


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
    pts = as_points(vertices, "vertices")
    if pts.shape[0] < 4:
        raise ValueError(f"vertices: need at least 4 points for a solid hull, got {pts.shape[0]}")
    box = axis_box_of(pts)
    if box is not None:
        lo, hi = box
        poly = Polytope(A=FRAME_A.copy(), b=np.concatenate([hi, -lo]))
        corners = np.ascontiguousarray(box_corners(lo[None], hi[None])[0])
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
    # The hull's vertices are known: `polytope_vertices` need not enumerate plane triples (for a
    # nearly flat hull it could not: its planes' intersections are ill-conditioned). They differ
    # from an enumeration from (A, b) in the last bits, so they travel with the polytope (an
    # attribute, not a field: pickled with it to a planner process, and to a recording), or a
    # plan would depend on which process built the obstacle.
    verts = np.ascontiguousarray(p[hull_vertices] * scale + origin, dtype=float)
    verts.flags.writeable = False
    object.__setattr__(poly, HULL_VERTICES, verts)
    _remember_vertices(poly, verts)
    return poly


def polytope_from_box(center: ArrayLike, size: ArrayLike) -> Polytope:
    """Axis-aligned box of full edge lengths `size` (each > 0) centred at `center`."""
    c = as_point(center, "center")
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
    pts = np.stack([as_point(p0, "p0"), as_point(p1, "p1")])
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
    verts = as_points(obstacle_vertices, "obstacle_vertices")
    A, b = normalised(corridor)
    if A.shape[0] == 0:
        return float("-inf")
    return float(np.max(np.min(verts @ A.T - b, axis=0)))
