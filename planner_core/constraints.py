"""Constraint rows and cost matrices of one segment as linear maps of its two end jets.

A segment's 10 control points are `[start_map @ J0; end_map @ J1]` (method.md), so
every hull quantity the planner constrains (control points, and the control points of
the `HULL_PIECES` de Casteljau pieces of the hodographs of orders 1..4) is a fixed
matrix times the stacked jet pair.

Column layout used by every row here ("30-layout"): the pair of jets
`(J0, J1)` of a segment, each (5, 3), flattened as `[J0.ravel(), J1.ravel()]`,
so column = side * 15 + order * 3 + axis.

Duration dependence is a pure power law (start/end maps scale column `order`
by Δ^order, hodographs scale row order k by Δ^-k), so all matrices are built
once at Δ = 1 and scaled, vectorised over segments.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from math import comb

import numpy as np
from numpy.typing import NDArray

from planner_core.bezier import (
    certificate_matrix,
    end_map,
    hodograph_matrix,
    stacked_pieces,
    start_map,
)
from planner_core.problem import DEGREE, JET_ORDER, N_CTRL, Bounds, FloatArray, Polytope

IntArray = NDArray[np.int64]

JET_COLS = 2 * JET_ORDER * 3  # 30
INF = 1e30  # what both QP backends treat as "no bound"

# Group kinds used by row metadata (diagnosis names them).
KIND_BOUND = 0
KIND_CORRIDOR = 1


HULL_PIECES = 3  # de Casteljau pieces per hodograph in the bound rows (measured: benchmarks/speed.py)


@lru_cache(maxsize=1)
def unit_templates() -> tuple[FloatArray, IntArray, IntArray, IntArray]:
    """Q(1) (10 + n, 10): ctrl points, then the control points of the `HULL_PIECES` de Casteljau
    pieces of the hodographs of orders 1..4 (`bezier.certificate_matrix`), over (side*5+order);
    power table; row order; row index (within its order).

    One hull over a degree-9 segment is up to 15x wider than the curve (a rest-to-rest segment:
    velocity 3.7x, snap 14.6x); the pieces' hulls are within 1.07 / 1.07 / 1.25 / 1.62x of it at
    3 pieces, and every row is still a linear map of the two jets."""
    smat = np.zeros((N_CTRL, 2 * JET_ORDER))
    smat[:JET_ORDER, :JET_ORDER] = start_map(1.0)
    smat[JET_ORDER:, JET_ORDER:] = end_map(1.0)
    blocks = [np.eye(N_CTRL)] + [certificate_matrix(k, HULL_PIECES) for k in range(1, 5)]
    q1 = np.vstack(blocks) @ smat
    row_order = np.concatenate([np.full(b.shape[0], k) for k, b in enumerate(blocks)])
    row_index = np.concatenate([np.arange(b.shape[0]) for b in blocks])
    col_order = np.tile(np.arange(JET_ORDER), 2)
    power = col_order[None, :] - row_order[:, None]
    return q1, power, row_order, row_index


def n_bound_points() -> int:
    """Certified hodograph points (orders 1..4, all pieces) per segment and axis."""
    return int(unit_templates()[0].shape[0]) - N_CTRL


def hull_maps(durations: FloatArray) -> FloatArray:
    """Per segment, the (10 + n, 10) map from one axis of (J0, J1) to ctrl + certified hodograph points."""
    q1, power, _, _ = unit_templates()
    d = np.asarray(durations, dtype=float)
    # integer powers -4..4: one small table per segment, then a gather (elementwise ** with an
    # integer array exponent goes through pow() 400 times a segment: ~5x slower at m = 1000)
    lo = int(power.min())
    table = d[:, None] ** np.arange(lo, int(power.max()) + 1, dtype=float)[None, :]
    # np.take gives C order (the compiled pass reads these maps row by row); fancy indexing did not
    out: FloatArray = np.take(table, (power - lo).ravel(), axis=1)
    out *= q1.ravel()
    return out.reshape(d.size, *q1.shape)


_CORR_Q_ROWS = np.arange(1, N_CTRL - 1)  # P^1..P^8 (P^0, P^9 are the fixed waypoints)


def _bound_q_rows() -> IntArray:
    """Hull rows of the bound constraints (the certified hodograph points, orders 1..4)."""
    return np.arange(N_CTRL, N_CTRL + n_bound_points())


@lru_cache(maxsize=1)
def _bound_meta() -> tuple[IntArray, IntArray, IntArray, NDArray[np.bool_]]:
    """Per box row (point * 3 + axis): order, point index, axis, depends on the start jet only."""
    q1, _, row_order, row_index = unit_templates()
    rows = _bound_q_rows()
    order = np.repeat(row_order[rows], 3)
    index = np.repeat(row_index[rows], 3)
    axis = np.tile(np.arange(3), rows.size)
    # read off the map (the zeros are structural: de Casteljau steps at u = 0 or 1 copy exactly):
    # a point depends on J0 only when its end-jet columns vanish
    half = np.repeat(np.all(q1[rows, JET_ORDER:] == 0.0, axis=1), 3)
    return order, index, axis, half


# --- bound rows: the box's axes and the horizontal norm's polygon ---------------------------

CODE_NORM = 3  # a bound row's direction code: 0..2 an axis, CODE_NORM a horizontal polygon direction


@lru_cache(maxsize=8)
def polygon_normals(sides: int) -> FloatArray:
    """(sides / 2, 2) unit normals of the edges of the regular polygon with vertices at angles
    2 pi j / sides on the circle, one per pair of opposite edges (angles pi (2 i + 1) / sides).
    A point c is inside the polygon of circumradius r iff |n_i . c| <= r cos(pi / sides) for all i."""
    ang = np.pi * (2.0 * np.arange(sides // 2) + 1.0) / sides
    out = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    out.setflags(write=False)
    return out


def polygon_excess(points: FloatArray, radius: FloatArray | float, sides: int) -> FloatArray:
    """(...,) max_i |n_i . (x, y)| - radius cos(pi / sides) of points (..., 2 or 3): > 0 outside the
    certifying polygon of the norm bound `radius` (broadcast against points[..., 0]; inf: none,
    -inf out). NaN stays NaN."""
    proj = np.abs(np.asarray(points)[..., :2] @ polygon_normals(sides).T)
    out: FloatArray = proj.max(axis=-1) - np.asarray(radius, dtype=float) * np.cos(np.pi / sides)
    return out


@dataclass(frozen=True)
class BoundLayout:
    """The bound rows of one segment, in their canonical order: the box rows (point * 3 + axis,
    as before norm bounds existed), then, for each order with a horizontal norm bound, each of
    its certified points' `sides / 2` polygon directions. Row value = direction . point."""

    point: IntArray  # certified hodograph point (hull row 10 + point) of each row
    code: IntArray  # 0..2 its axis, CODE_NORM a horizontal direction
    direction: FloatArray  # (R, 3): the unit axis or (cos, sin, 0)
    order: IntArray
    lo: FloatArray
    hi: FloatArray
    start_only: NDArray[np.bool_]  # depends on the start jet only
    end_only: NDArray[np.bool_]


@lru_cache(maxsize=16)
def _layout_structure(norm_orders: tuple[bool, ...], sides: int) -> tuple[IntArray, IntArray, FloatArray, IntArray]:
    order, _, axis, _ = _bound_meta()
    q_order = unit_templates()[2][_bound_q_rows()]  # order of each certified point
    point = np.repeat(np.arange(q_order.size), 3)
    code = axis.astype(np.int64)
    direction = np.eye(3)[axis]
    orders = order.astype(np.int64)
    normals = polygon_normals(sides)
    nd = normals.shape[0]
    for k in range(1, 5):
        if not norm_orders[k - 1]:
            continue
        pts = np.flatnonzero(q_order == k)
        point = np.concatenate([point, np.repeat(pts, nd)])
        code = np.concatenate([code, np.full(pts.size * nd, CODE_NORM)])
        dirs = np.zeros((nd, 3))
        dirs[:, :2] = normals
        direction = np.concatenate([direction, np.tile(dirs, (pts.size, 1))])
        orders = np.concatenate([orders, np.full(pts.size * nd, k)])
    for a in (point, code, direction, orders):
        a.setflags(write=False)
    return point.astype(np.int64), code, direction, orders


@lru_cache(maxsize=64)
def _bound_layout(key: bytes, norm_orders: tuple[bool, ...], sides: int) -> BoundLayout:
    vals = np.frombuffer(key, dtype=np.float64)
    lo4, hi4, hor = vals[:12].reshape(4, 3), vals[12:24].reshape(4, 3), vals[24:28]
    point, code, direction, order = _layout_structure(norm_orders, sides)
    box = code < CODE_NORM
    axis = np.where(box, code, 0)
    r = hor[order - 1] * np.cos(np.pi / sides)
    lo = np.where(box, lo4[order - 1, axis], -r)
    hi = np.where(box, hi4[order - 1, axis], r)
    q1 = unit_templates()[0]
    qrows = _bound_q_rows()[point]
    start_only = np.all(q1[qrows, JET_ORDER:] == 0.0, axis=1)
    end_only = np.all(q1[qrows, :JET_ORDER] == 0.0, axis=1)
    for a in (lo, hi, start_only, end_only):
        a.setflags(write=False)
    return BoundLayout(point, code, direction, order, lo, hi, start_only, end_only)


def bound_layout(bounds: Bounds) -> BoundLayout:
    """The bound rows `bounds` needs (cached per distinct bounds)."""
    return _bound_layout(bounds.key(), tuple(bool(v) for v in np.isfinite(bounds.horizontal)), bounds.sides)


def bound_sides() -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """Per box row (point * 3 + axis): depends on the start jet only; on the end jet only."""
    q1 = unit_templates()[0]
    rows = _bound_q_rows()
    a_only = np.repeat(np.all(q1[rows, JET_ORDER:] == 0.0, axis=1), 3)
    b_only = np.repeat(np.all(q1[rows, :JET_ORDER] == 0.0, axis=1), 3)
    return a_only, b_only


def bound_rows(hull: FloatArray, bounds: Bounds) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Rows (R, 30), lower and upper limits of the dynamic-bound constraints of one segment
    (`bound_layout`: the box's, then the horizontal norm's polygon)."""
    lay = bound_layout(bounds)
    q = hull[N_CTRL + lay.point]  # (R, 10)
    rows: FloatArray = (q[:, :, None] * lay.direction[:, None, :]).reshape(q.shape[0], 3 * q.shape[1])
    return rows, np.asarray(lay.lo), np.asarray(lay.hi)


def corridor_rows(hull: FloatArray, poly: Polytope) -> tuple[FloatArray, FloatArray]:
    """Rows (8 f, 30) and upper limits of 'P^1..P^8 inside poly' for one segment."""
    rows: FloatArray = np.kron(hull[_CORR_Q_ROWS], poly.A).astype(np.float64)
    return rows, np.tile(poly.b, _CORR_Q_ROWS.size)


def corridor_half_mask(n_faces: int) -> NDArray[np.bool_]:
    """Corridor rows that depend only on the start jet (P^1..P^4)."""
    return np.repeat(_CORR_Q_ROWS <= JET_ORDER - 1, n_faces)




# --- costs -------------------------------------------------------------------


def bernstein_gram(n: int) -> FloatArray:
    """∫_0^1 B_i^n(u) B_j^n(u) du."""
    i = np.arange(n + 1)
    ci = np.array([comb(n, a) for a in i], dtype=float)
    c2 = np.array([[comb(2 * n, a + b) for b in i] for a in i], dtype=float)
    return np.asarray(np.outer(ci, ci) / (c2 * (2 * n + 1)))


@lru_cache(maxsize=8)
def unit_cost(order: int) -> tuple[FloatArray, FloatArray]:
    q1 = unit_templates()[0]
    # the plain hodograph (the cost integrates the curve itself, not the certificate's pieces)
    m = hodograph_matrix(order, 1.0) @ q1[:N_CTRL]  # (10-order, 10)
    k1 = m.T @ bernstein_gram(DEGREE - order) @ m
    col_order = np.tile(np.arange(JET_ORDER), 2)
    # ∫_0^Δ |x^(k)(t)|^2 dt = Δ * (Δ^-k)^2 * ... ; column scaling Δ^order(c)
    cost_power = 1 - 2 * order + col_order[:, None] + col_order[None, :]
    return k1, cost_power.astype(float)


def cost_matrices(durations: FloatArray, order: int = 4) -> FloatArray:
    """Per segment (10, 10) per-axis matrix K with ∫|x^(order)|^2 dt = Σ_axis z_d' K z_d."""
    k1, power = unit_cost(order)
    d = np.asarray(durations, dtype=float)
    return k1[None] * d[:, None, None] ** power[None]


def integrated_cost(control_points: FloatArray, durations: FloatArray, order: int = 4) -> float:
    """∫ |x^(order)(t)|^2 dt over a whole trajectory, from its control points."""
    from planner_core.bezier import hodographs

    pts = hodographs(control_points, order, durations)
    gram = bernstein_gram(DEGREE - order)
    # gram @ pts is one batched matmul; the three-operand einsum looped in C without BLAS
    per_seg = np.einsum("sid,sid->s", pts, np.matmul(gram, pts)) * np.asarray(durations, dtype=float)
    return float(np.sum(per_seg))


@dataclass(frozen=True)
class SegmentRows:
    """All hull rows of one segment in the 30-layout, with metadata for diagnosis."""

    rows: FloatArray  # (n, 30)
    lo: FloatArray  # (n,)
    hi: FloatArray  # (n,)
    half: NDArray[np.bool_]  # rows that depend only on the start jet
    kind: IntArray  # KIND_BOUND / KIND_CORRIDOR
    order: IntArray  # derivative order for bound rows, 0 for corridor rows


def segment_rows(hull: FloatArray, bounds: Bounds, poly: Polytope | None) -> SegmentRows:
    brows, blo, bhi = bound_rows(hull, bounds)
    lay = bound_layout(bounds)
    bhalf = lay.start_only
    border = lay.order
    if poly is None or poly.A.shape[0] == 0:
        return SegmentRows(
            brows,
            np.clip(blo, -INF, INF),
            np.clip(bhi, -INF, INF),
            bhalf,
            np.full(brows.shape[0], KIND_BOUND),
            border,
        )
    crows, chi = corridor_rows(hull, poly)
    n_c = crows.shape[0]
    return SegmentRows(
        np.vstack([brows, crows]),
        np.clip(np.concatenate([blo, np.full(n_c, -np.inf)]), -INF, INF),
        np.clip(np.concatenate([bhi, chi]), -INF, INF),
        np.concatenate([bhalf, corridor_half_mask(poly.A.shape[0])]),
        np.concatenate([np.full(brows.shape[0], KIND_BOUND), np.full(n_c, KIND_CORRIDOR)]),
        np.concatenate([border, np.zeros(n_c, dtype=np.int64)]),
    )


def certified_points(ctrl: FloatArray, k: int, durations: FloatArray) -> FloatArray:
    """(s, n_k, 3) the order-k values the planner's bound rows certify for segments (s, 10, 3):
    the control points of the `HULL_PIECES` de Casteljau pieces of each hodograph."""
    from planner_core.bezier import hodographs

    return np.asarray(np.matmul(stacked_pieces(DEGREE - k, HULL_PIECES), hodographs(ctrl, k, durations)))
