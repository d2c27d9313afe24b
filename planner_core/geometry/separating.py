"""Separating a segment from a convex obstacle: the maximum-margin plane (a hard-margin SVM,
the closest pair as its fallback) one pair at a time, and in closed form over feature pairs for
many (segment, obstacle) pairs at once (`separations`)."""


from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planner_core.geometry.common import IntArray
from planner_core.problem import FloatArray
from planner_core.qp import SENSE_EQUALITY, DaqpSolver, QPStatus

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


def polytope_edges(verts: FloatArray, A: FloatArray, b: FloatArray) -> IntArray:
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


def row_dot(x: FloatArray, y: FloatArray) -> FloatArray:
    return np.asarray(np.sum(x * y, axis=-1))


def _segment_pairs(p: FloatArray, d1: FloatArray, q: FloatArray, d2: FloatArray) -> tuple[FloatArray, FloatArray]:
    """Closest points of segments p + s d1 to segments q + t d2 (any shapes that broadcast, last
    axis 3): e.g. (s, 1, 3) against (1, E, 3) for every pair, or (P, 1, 3) against (P, E, 3).

    Ericson, Real-Time Collision Detection, 5.1.9, with the degenerate cases (a
    point for a segment, parallel segments) as array masks. Returns the two points
    of each pair, each of the broadcast shape.
    """
    a = row_dot(d1, d1)
    e = row_dot(d2, d2)
    c = row_dot(d1, p - q)
    f = row_dot(d2, p - q)
    bb = row_dot(d1, d2)
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
class PaddedShapes:
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


def padded_shapes(verts: Sequence[FloatArray], edges: Sequence[IntArray], planes: Sequence[tuple[FloatArray, FloatArray]]) -> PaddedShapes:
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
    return PaddedShapes(pv, e0, e1 - e0, pA, pb, np.einsum("nfd,ngd->nfg", pA, pA), tol)


def separations_padded(p0: FloatArray, p1: FloatArray, sh: PaddedShapes, ks: IntArray | None) -> tuple[FloatArray, FloatArray]:
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
    sh = padded_shapes([verts], [polytope_edges(verts, A, b)], [(A, b)])
    one = PaddedShapes(sh.verts[0], sh.edge0[0], sh.edged[0], sh.A[0], sh.b[0], sh.AA[0], sh.tol[0])
    return separations_padded(p0, p1, one, None)
