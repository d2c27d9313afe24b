"""Safe corridors: one convex polytope per segment, built from obstacle polytopes.

A corridor bounds the vehicle *centre* (the planner keeps every control point
of segment j inside corridor j). With vehicle radius r, corridor j = {x : A x <= b}
(unit rows) satisfies, by construction:

- Containment: the straight segment [W_j, W_{j+1}] is inside, at distance >= r
  from every obstacle plane (so the curve has room to bend) and inside the map
  planes (the vehicle centre stays in the map box shrunk by r).
- Exclusion (checkable certificate): for every obstacle O there is one corridor
  plane with all vertices of O at signed distance >= r beyond it, so the ball of
  radius r around any corridor point misses O.
- Room: an obstacle's plane has the maximum-margin normal between the segment
  and the obstacle (hard-margin SVM, a 4-variable QP) and is pushed to the
  obstacle side as far as safety allows: offset = min_v a.v - r. The segment
  then keeps clearance gap - r >= r from it, where gap = min_v a.v - max_p a.p.
- Blocked: a segment is flyable only if the segment inflated by r and the
  obstacle inflated by r are disjoint (gap >= 2r); otherwise CorridorError.
  Obstacles already kept r beyond the shrunk map box count as outside the map.
- Economy: obstacles within `influence` of the segment always get a plane;
  farther ones only when no existing plane already certifies them. Planes that
  are not facets of the corridor are then dropped unless one is the only
  certificate of some obstacle (removing it would not change the region, but
  the certificate is what makes exclusion checkable with one matrix product).
"""

from __future__ import annotations

from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from functools import lru_cache
from itertools import combinations

import daqp
import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner_core.problem import FloatArray, Polytope

IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]

CERT_TOL = 1e-10  # slack on the certificate test; the offsets are exact up to rounding
DEFAULT_INFLUENCE_MARGIN = 3.0  # metres beyond the segment length (plus 2r) that get a plane
_HULL_TOL = 1e-9  # relative to the point cloud's extent
_DET_TOL = 1e-12  # unit normals: |det| below this means three planes share no single point
_CHUNK = 20000  # triples per vectorised batch (bounds memory for big hulls)


class CorridorError(ValueError):
    """No safe convex corridor exists; names the segment/waypoint/obstacle at fault."""

    def __init__(
        self,
        message: str,
        *,
        segment: int | None = None,
        waypoint: int | None = None,
        obstacle: int | None = None,
    ) -> None:
        super().__init__(message)
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


@lru_cache(maxsize=64)
def _cached_triples(k: int) -> IntArray:
    idx = np.fromiter(
        (i for t in combinations(range(k), 3) for i in t), dtype=np.intp
    ).reshape(-1, 3)
    idx.setflags(write=False)
    return idx


def _triple_chunks(k: int) -> list[IntArray]:
    """All index triples i<j<l of range(k), in batches."""
    if k < 3:
        return []
    if k <= 64:
        return [_cached_triples(k)]
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
    if not _is_bounded(A):
        raise ValueError(f"{name}: polytope is unbounded (its planes do not enclose a region)")
    verts = _vertices(A, b)
    if verts.shape[0] == 0:
        raise ValueError(f"{name}: polytope is empty (its planes have no common point)")
    verts.flags.writeable = False
    _VERTEX_CACHE[key] = verts
    while len(_VERTEX_CACHE) > _VERTEX_CACHE_SIZE:
        _VERTEX_CACHE.popitem(last=False)
    return verts


# --- convex hull (vertices -> H-representation) -----------------------------


def _dedup_planes(A: FloatArray, b: FloatArray, tol: float) -> tuple[FloatArray, FloatArray]:
    if A.shape[0] <= 1:
        return A, b
    key = np.concatenate([A, b[:, None]], axis=1)
    diff = np.max(np.abs(key[:, None, :] - key[None, :, :]), axis=-1)
    keep = ~np.tril(diff <= tol, -1).any(axis=1)
    return A[keep], b[keep]


def _hull_planes(p: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Facet planes of the hull of points p (extent ~1): every supporting triple plane."""
    normals: list[FloatArray] = []
    offsets: list[FloatArray] = []
    for idx in _triple_chunks(p.shape[0]):
        n = np.cross(p[idx[:, 1]] - p[idx[:, 0]], p[idx[:, 2]] - p[idx[:, 0]])
        norm = np.linalg.norm(n, axis=1)
        good = norm > 1e-12
        n = n[good] / norm[good, None]
        d = np.einsum("td,td->t", n, p[idx[good, 0]])
        s = p @ n.T - d  # (k, T) signed distances of all points
        below = np.max(s, axis=0) <= _HULL_TOL
        above = np.min(s, axis=0) >= -_HULL_TOL
        normals += [n[below], -n[above]]
        offsets += [d[below], -d[above]]
    A = np.concatenate(normals) if normals else np.zeros((0, 3))
    b = np.concatenate(offsets) if offsets else np.zeros(0)
    return _dedup_planes(A, b, 1e-7)


def polytope_from_vertices(vertices: ArrayLike) -> Polytope:
    """H-representation of the convex hull of `vertices` (k, 3).

    Rows of A are unit normals, one per facet (no redundant rows). Cost is
    O(k^4) by plane triples, meant for obstacles of tens of vertices.
    Raises ValueError for fewer than 4 points, non-finite values, or points
    that are collinear or coplanar (the hull would have no volume).
    """
    pts = _as_points(vertices, "vertices")
    if pts.shape[0] < 4:
        raise ValueError(f"vertices: need at least 4 points for a solid hull, got {pts.shape[0]}")
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
    A, b = _hull_planes(p)
    return Polytope(A=A, b=b * scale + A @ origin)


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
    x, _, flag, _ = daqp.solve(_SVM_H, _SVM_F, rows, -np.ones(k), np.full(k, -1e30), sense)
    if flag == -1:
        # a very thin gap makes the SVM badly scaled, and daqp may call it infeasible:
        # settle it with the closest-point pair, which is always well posed
        return _closest_pair_normal(p, v)
    w = np.asarray(x[:3], dtype=float)
    norm = float(np.linalg.norm(w))
    if flag not in (1, 2) or not np.isfinite(norm) or norm == 0.0:
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
    sense = np.concatenate([np.zeros(n, dtype=np.int32), np.full(2, 5, dtype=np.int32)])
    x, _, flag, _ = daqp.solve(h, f, eq, upper, lower, sense, eps_prox=-1.0)
    if flag not in (1, 2):
        return None
    d = np.asarray(m @ np.asarray(x, dtype=float), dtype=float)  # p* - v*
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


# --- obstacle set -----------------------------------------------------------------


@dataclass(frozen=True)
class _Obstacles:
    """All obstacles' vertices stacked, with offsets and bounding spheres."""

    verts: tuple[FloatArray, ...]
    stacked: FloatArray  # (N, 3)
    starts: IntArray  # (n,) first row of each obstacle in `stacked`
    centres: FloatArray  # (n, 3)
    radii: FloatArray  # (n,)
    planes: tuple[tuple[FloatArray, FloatArray], ...]

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
    verts: list[FloatArray] = []
    planes: list[tuple[FloatArray, FloatArray]] = []
    for i, obs in enumerate(obstacles):
        name = f"obstacles[{first_index + i}]"
        if not isinstance(obs, Polytope):
            raise ValueError(f"{name}: expected a Polytope, got {type(obs).__name__}")
        planes.append(normalised(obs, name))
        verts.append(polytope_vertices(obs, name))
    if not verts:
        empty = np.zeros((0, 3))
        return _Obstacles((), empty, np.zeros(0, dtype=np.intp), empty, np.zeros(0), ())
    counts = np.array([v.shape[0] for v in verts])
    centres = np.stack([v.mean(axis=0) for v in verts])
    radii = np.array([np.max(np.linalg.norm(v - c, axis=1)) for v, c in zip(verts, centres, strict=True)])
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]]).astype(np.intp)
    return _Obstacles(tuple(verts), np.concatenate(verts), starts, centres, radii, tuple(planes))


def _segment_point_distance(p0: FloatArray, p1: FloatArray, c: FloatArray) -> FloatArray:
    """(s, n) distance from segments [p0_s, p1_s] to points c_n."""
    d = p1 - p0  # (s, 3)
    dd = np.einsum("sd,sd->s", d, d)
    rel = c[None, :, :] - p0[:, None, :]  # (s, n, 3)
    t = np.einsum("snd,sd->sn", rel, d) / np.where(dd > 0, dd, 1.0)[:, None]
    t = np.clip(t, 0.0, 1.0)
    closest = p0[:, None, :] + t[..., None] * d[:, None, :]
    return np.asarray(np.linalg.norm(c[None, :, :] - closest, axis=-1))


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


def _check_waypoints_clear(ctx: _Context) -> None:
    obs = ctx.obs
    if obs.n == 0:
        return
    near = (
        np.linalg.norm(ctx.waypoints[:, None, :] - obs.centres[None, :, :], axis=-1) - obs.radii
        < ctx.radius
    )
    for i, k in zip(*np.nonzero(near), strict=True):
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


def _obstacle_plane(ctx: _Context, j: int, k: int) -> tuple[FloatArray, float]:
    """The roomiest safe plane (unit a, offset) between segment j and obstacle k."""
    seg = ctx.waypoints[j : j + 2]
    verts = ctx.obs.verts[k]
    normal, gap = separation(seg, verts)
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
) -> tuple[FloatArray, FloatArray]:
    """Add a plane for each candidate obstacle (nearest first) that needs one.

    must[k]: obstacle k gets its own plane even if already certified.
    """
    certs = ctx.obs.margins(A, b)
    certified = np.any(certs >= ctx.radius - CERT_TOL, axis=1)
    new_A: list[FloatArray] = []
    new_b: list[float] = []
    for k in candidates:
        if certified[k] and not must[k]:
            continue
        a, off = _obstacle_plane(ctx, j, int(k))
        new_A.append(a)
        new_b.append(off)
        certified |= ctx.obs.margins(a[None, :], np.array([off]))[:, 0] >= ctx.radius - CERT_TOL
    if not new_A:
        return A, b
    return np.concatenate([A, np.stack(new_A)]), np.concatenate([b, np.array(new_b)])


def _finish(ctx: _Context, A: FloatArray, b: FloatArray) -> Polytope:
    keep = _prune(A, b, ctx.obs.margins(A, b), ctx.radius, ctx.aux)
    return Polytope(A=np.ascontiguousarray(A[keep]), b=np.ascontiguousarray(b[keep]))


def _segment_corridor(ctx: _Context, j: int, lower: FloatArray, influence: float) -> Polytope:
    """Corridor of segment j; lower[k] bounds its distance to obstacle k from below."""
    A, b = ctx.map_A, ctx.map_b
    outside_map = np.any(ctx.obs.margins(A, b) >= ctx.radius - CERT_TOL, axis=1)
    order = np.argsort(lower, kind="stable")
    order = order[~outside_map[order]]
    A, b = _add_planes(ctx, j, A, b, order, lower < influence)
    return _finish(ctx, A, b)


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

    influence: obstacles whose distance to a segment may be below this get a
    plane of their own; default segment length + 3 m + 2 x radius. Farther
    obstacles get one only if the corridor does not already exclude them.
    Raises CorridorError for a waypoint outside the map box shrunk by radius,
    a waypoint inside an inflated obstacle, or a blocked segment; ValueError
    for malformed input.
    """
    wps = _validate_waypoints(waypoints)
    r = _validate_radius(radius)
    if influence is not None and not (np.isfinite(influence) and influence >= 0.0):
        raise ValueError(f"influence: must be finite and >= 0, got {influence}")
    obs = _prepare_obstacles(obstacles)
    ctx = _context(wps, obs, map_box, r)
    _check_waypoints_in_map(ctx)
    _check_waypoints_clear(ctx)
    p0, p1 = wps[:-1], wps[1:]
    lower = np.maximum(_segment_point_distance(p0, p1, obs.centres) - obs.radii, 0.0)
    lengths = np.linalg.norm(p1 - p0, axis=1)
    reach = lengths + DEFAULT_INFLUENCE_MARGIN if influence is None else np.full_like(lengths, influence)
    # Anything within 2r could block the segment, so it must be examined.
    reach = np.maximum(reach, 2.0 * r + 1e-9)
    return tuple(_segment_corridor(ctx, j, lower[j], float(reach[j])) for j in range(wps.shape[0] - 1))


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
    of the old obstacles, which then are only counted.
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
    lower = np.maximum(_segment_point_distance(wps[:-1], wps[1:], new.centres) - new.radii, 0.0)
    out = list(corridors)
    changed: list[int] = []
    for j, corridor in enumerate(corridors):
        A, b = normalised(corridor, f"corridors[{j}]")
        if new.n == 0 or np.all(np.any(new.margins(A, b) >= r - CERT_TOL, axis=1)):
            continue
        order = np.argsort(lower[j], kind="stable")
        A2, b2 = _add_planes(ctx, j, A, b, order, np.zeros(new.n, dtype=bool))
        if prune:
            out[j] = _finish(full, A2, b2)
        else:
            keep = _first_of_duplicates(A2, b2)
            out[j] = Polytope(A=np.ascontiguousarray(A2[keep]), b=np.ascontiguousarray(b2[keep]))
        changed.append(j)
    return tuple(out), changed
