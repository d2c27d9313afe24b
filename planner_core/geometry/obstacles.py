"""The obstacle set as the builders read it (vertices, edges, planes, bounding boxes, padded
for batching), the map box's planes and each segment's analysis box."""


from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike

from planner_core.geometry.common import IntArray
from planner_core.geometry.polytopes import (
    BOX_EDGES,
    as_point,
    box_corners,
    box_extents,
    normalised,
    polytope_vertices,
)
from planner_core.geometry.separating import PaddedShapes, padded_shapes, polytope_edges, row_dot
from planner_core.problem import FloatArray, Polytope

# --- obstacle set -----------------------------------------------------------------


@dataclass(frozen=True)
class Obstacles:
    """All obstacles' vertices stacked, with offsets, bounding spheres and boxes, and padded."""

    verts: tuple[FloatArray, ...]
    stacked: FloatArray  # (N, 3)
    starts: IntArray  # (n,) first row of each obstacle in `stacked`
    centres: FloatArray  # (n, 3)
    radii: FloatArray  # (n,)
    planes: tuple[tuple[FloatArray, FloatArray], ...]
    lo: FloatArray  # (n, 3) bounding boxes of the vertices
    hi: FloatArray
    shapes: PaddedShapes | None  # None without obstacles

    @property
    def n(self) -> int:
        return len(self.verts)

    def margins(self, A: FloatArray, b: FloatArray) -> FloatArray:
        """(n, P) min signed distance of each obstacle's vertices beyond each plane."""
        if self.n == 0 or A.shape[0] == 0:
            return np.full((self.n, A.shape[0]), -np.inf)
        s = self.stacked @ A.T - b
        return np.minimum.reduceat(s, self.starts, axis=0)


def prepare_obstacles(obstacles: Sequence[Polytope], first_index: int = 0) -> Obstacles:
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
        return Obstacles((), empty, np.zeros(0, dtype=np.intp), empty, np.zeros(0), (), empty, empty, None)
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
        is_box, lo, hi = box_extents(An, bn)
        is_box &= fine
        corners = box_corners(lo, hi)
        if len(six) == n and bool(np.all(is_box)):
            return _boxes(corners, An, bn, lo, hi)
        for row in np.flatnonzero(is_box).tolist():
            i = six[row]
            verts[i] = corners[row]
            planes[i] = (An[row], bn[row])
            edges[i] = BOX_EDGES
    for i, obs in enumerate(obstacles):
        if verts[i] is not None:
            continue
        name = f"obstacles[{first_index + i}]"
        A, b = normalised(obs, name)
        v = polytope_vertices(obs, name)
        verts[i], planes[i], edges[i] = v, (A, b), polytope_edges(v, A, b)
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
    return Obstacles(tuple(vs), stacked, starts, centres, radii, tuple(ps), lo, hi, padded_shapes(vs, es, ps))


def _boxes(corners: FloatArray, A: FloatArray, b: FloatArray, lo: FloatArray, hi: FloatArray) -> Obstacles:
    """`prepare_obstacles` when every obstacle is an axis-aligned box: all in array operations."""
    n = corners.shape[0]
    e = BOX_EDGES
    e0 = corners[:, e[:, 0]]
    shapes = PaddedShapes(corners, e0, corners[:, e[:, 1]] - e0, A, b, np.einsum("nfd,ngd->nfg", A, A),
                     1e-12 * np.maximum(1.0, np.max(np.abs(corners), axis=(1, 2))))
    radii = 0.5 * np.linalg.norm(hi - lo, axis=1)
    return Obstacles(tuple(corners), corners.reshape(-1, 3), np.arange(n, dtype=np.intp) * 8, 0.5 * (lo + hi),
                      radii, tuple(zip(A, b, strict=True)), lo, hi, shapes)


def segment_point_distance(p0: FloatArray, p1: FloatArray, c: FloatArray) -> FloatArray:
    """(s, n) distance from segments [p0_s, p1_s] to points c_n."""
    return pair_point_distance(p0[:, None, :], p1[:, None, :], c[None, :, :])


def pair_point_distance(p0: FloatArray, p1: FloatArray, c: FloatArray) -> FloatArray:
    """Distance from segments [p0, p1] to points c, elementwise over broadcast leading axes."""
    d = p1 - p0
    dd = row_dot(d, d)
    t = np.clip(row_dot(c - p0, d) / np.where(dd > 0, dd, 1.0), 0.0, 1.0)
    return np.asarray(np.linalg.norm(c - (p0 + t[..., None] * d), axis=-1))


# --- map box ------------------------------------------------------------------------


def map_planes(map_box: tuple[ArrayLike, ArrayLike] | None, radius: float) -> tuple[FloatArray, FloatArray]:
    if map_box is None:
        return np.zeros((0, 3)), np.zeros(0)
    lo = as_point(map_box[0], "map_box.min")
    hi = as_point(map_box[1], "map_box.max")
    if np.any(hi - lo <= 2.0 * radius):
        axis = int(np.argmax(hi - lo <= 2.0 * radius))
        raise ValueError(
            f"map_box: extent {hi[axis] - lo[axis]:g} along axis {axis} leaves no room "
            f"for a vehicle of radius {radius:g}"
        )
    eye = np.eye(3)
    return np.concatenate([eye, -eye]), np.concatenate([hi - radius, -(lo + radius)])


def analysis_box(waypoints: FloatArray, obs: Obstacles) -> tuple[FloatArray, FloatArray]:
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



def min_over_vertices(obs: Obstacles, normals: FloatArray, ks: IntArray) -> FloatArray:
    """min over obstacle ks[i]'s vertices of normals[i] . v, for every i."""
    if ks.shape[0] == 0 or obs.shapes is None:
        return np.zeros(ks.shape[0])
    return np.asarray(np.min(np.einsum("pd,pvd->pv", normals, obs.shapes.verts[ks]), axis=1))
