"""What the general jet solver (`planner_core.jets`) keeps per problem: `ProblemCache` (hull
maps, limits, each segment's row blocks `SegBlocks` built on first use, cost blocks), the bound
row layout `BoundRowSpec`, the `ExtraRows` protocol (time-resolved separation rows) and
`tighten` (every limit moved inwards by `MARGIN`, so a solution meets the untightened rows).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from planner_core.constraints import (
    INF,
    KIND_BOUND,
    KIND_CORRIDOR,
    SegmentRows,
    cost_matrices,
    hull_maps,
    segment_rows,
)
from planner_core.problem import FloatArray, Problem

MARGIN = 1e-6  # relative tightening of every limit
BLOCKS_KEPT = 64  # segments whose row blocks a ProblemCache keeps (a window touches ~10)


@dataclass(frozen=True)
class SegBlocks:
    """One segment's rows: value = c0 + A @ Ja + B @ Jb (Ja, Jb: derivative rows of its jets, 12 each).

    Rows are ordered [start-jet only | both jets | end-jet only] (n1, n2, n3 rows),
    so every role a QP needs is a contiguous slice (a view, no copy):
    'half' = [0:n1], 'a' (end jet fixed) = [0:n1+n2], 'b' (start jet fixed) = [n1:], 'ab' = all.
    """

    A: FloatArray  # (n, 12)
    B: FloatArray  # (n, 12)
    c0: FloatArray  # (n,) contribution of the two (fixed) waypoint positions
    lo: FloatArray  # untightened limits
    hi: FloatArray
    lo_t: FloatArray  # tightened limits
    hi_t: FloatArray
    seg: NDArray[np.int64]
    kind: NDArray[np.int64]
    order: NDArray[np.int64]
    n1: int
    n2: int

    @cached_property
    def lim(self) -> FloatArray:
        """(4, n): tightened lo, hi, untightened lo, hi (one slice per QP instead of four)."""
        return np.stack([self.lo_t, self.hi_t, self.lo, self.hi])

    @cached_property
    def meta(self) -> NDArray[np.int64]:
        """(3, n): segment, kind, order of each row."""
        return np.stack([self.seg, self.kind, self.order])

    def role(self, role: str) -> slice:
        n = self.kind.size
        return {
            "half": slice(0, self.n1),
            "a": slice(0, self.n1 + self.n2),
            "b": slice(self.n1, n),
            "ab": slice(0, n),
        }[role]

    def dead(self, role: str) -> slice:
        """Rows that involve only the fixed jet in roles 'a' / 'b' (constants to check)."""
        n = self.kind.size
        return slice(self.n1 + self.n2, n) if role == "a" else slice(0, self.n1)


def _bound_groups(start_only: NDArray[np.bool_], end_only: NDArray[np.bool_]) -> tuple[NDArray[np.int64], int, int]:
    """Permutation of the bound rows into [start only | both | end only] and group sizes."""
    both = ~start_only & ~end_only
    perm = np.concatenate([np.flatnonzero(start_only), np.flatnonzero(both), np.flatnonzero(end_only)])
    return perm, int(start_only.sum()), int(both.sum())


@dataclass(frozen=True)
class BoundRowSpec:
    """The vehicle-bound rows of one segment, in block order [start only | both | end only]
    (`constraints.bound_layout`, permuted): what the row builders of `window` read."""

    point: NDArray[np.int64]  # the certified hodograph point of each row
    code: NDArray[np.int64]  # its axis (0..2) or `constraints.CODE_NORM` (a horizontal direction)
    direction: FloatArray  # (nb, 3) the direction of each row: an axis or a horizontal one
    order: NDArray[np.int64]  # the derivative order of each row
    n_start: int  # rows on the start jet only
    n_both: int  # rows on both jets (the end-only rows follow)
    lo: FloatArray  # limits, clipped to +-INF
    hi: FloatArray
    lo_t: FloatArray  # the same, tightened (`tighten`)
    hi_t: FloatArray

    @property
    def size(self) -> int:
        return int(self.point.size)


class ProblemCache:
    """Everything that depends only on durations, bounds and corridors, built once per problem.

    Hull maps and limits are vectorised over segments; each segment's row
    blocks are built on first use (the iterative pass stacks the rows near its
    window itself, in `window.py`, so the general path only pays for the few
    segments it touches). The hull maps of every segment (`hull`, ~7 MB at
    m = 1000) are built only for the compiled pass, which reads them all;
    the numpy paths build those of the segments they touch (`hull_of`).

    Bound rows (`constraints.bound_layout`, in block order): `bound_spec` (a `BoundRowSpec`).
    """

    def __init__(self, problem: Problem, extra_rows: ExtraRows | None = None) -> None:
        from planner_core.constraints import bound_layout

        self.problem = problem
        # general rows on control points (planner_core.separation.SeparationRows: the fleet's
        # separation), read only by the general path (`assemble`); None: none
        self.extra_rows = extra_rows
        self.durations = problem.durations
        # the segments the general path touched last: a recovery re-solves the same few again and
        # again, and a long mission's many recoveries would otherwise keep ~0.1 MB a segment
        self._blocks: dict[int, SegBlocks] = {}
        self._cost: dict[int, FloatArray] = {}
        lay = bound_layout(problem.bounds)
        perm, n_start, n_both = _bound_groups(lay.start_only, lay.end_only)
        lo = np.clip(lay.lo[perm], -INF, INF)
        hi = np.clip(lay.hi[perm], -INF, INF)
        lo_t, hi_t = tighten(lo, hi)
        self.bound_spec = BoundRowSpec(
            lay.point[perm], lay.code[perm], np.ascontiguousarray(lay.direction[perm]),
            lay.order[perm].astype(np.int64), n_start, n_both, lo, hi, lo_t, hi_t,
        )

    @cached_property
    def hull(self) -> FloatArray:
        """(S, 10 + n, 10) `hull_maps` of every segment."""
        return hull_maps(self.durations)

    def hull_of(self, segments: NDArray[np.int64] | int) -> FloatArray:
        """`hull[segments]`, without building every segment's maps when they are not built yet
        (the maps are per segment: the same numbers either way)."""
        if "hull" in self.__dict__:
            return np.asarray(self.hull[segments])
        if isinstance(segments, int):
            one: FloatArray = hull_maps(self.durations[segments : segments + 1])[0]
            return one
        return hull_maps(self.durations[segments])

    def bound_rows(self, s: int) -> tuple[FloatArray, FloatArray, FloatArray]:
        """Bound rows of segment s in block order: (A (R, 12), B (R, 12), c0 (R,))."""
        qb = self.hull_of(s)[10:][self.bound_spec.point]  # (R, 10) the certified point of each row
        nb = qb.shape[0]
        dirs = self.bound_spec.direction
        rows_a = (qb[:, 1:5, None] * dirs[:, None, :]).reshape(nb, 12)
        rows_b = (qb[:, 6:10, None] * dirs[:, None, :]).reshape(nb, 12)
        w = self.problem.waypoints
        # direction . waypoint: exactly the coordinate for an axis row (products with 0 and 1)
        c0 = qb[:, 0] * (dirs @ w[s]) + qb[:, 5] * (dirs @ w[s + 1])
        return rows_a, rows_b, c0

    def rows(self, s: int) -> SegmentRows:
        return segment_rows(self.hull_of(s), self.problem.bounds, self.problem.corridor(s))

    def blocks(self, s: int) -> SegBlocks:
        blk = self._blocks.pop(s, None)  # re-inserted below: the dict's order is last use
        if blk is None:
            blk = self._build_blocks(s)
            if self.extra_rows is not None:
                blk = self._with_extra(blk, s, self.extra_rows)
            if len(self._blocks) >= BLOCKS_KEPT:
                del self._blocks[next(iter(self._blocks))]  # the least recently used
        self._blocks[s] = blk
        return blk

    def _build_blocks(self, s: int) -> SegBlocks:
        n1, n2 = self.bound_spec.n_start, self.bound_spec.n_both
        poly = self.problem.corridor(s)
        nb = self.bound_spec.order.size
        kb = np.full(nb, KIND_BOUND, dtype=np.int64)
        bA, bB, bc0 = self.bound_rows(s)
        if poly is None or poly.A.shape[0] == 0:
            return SegBlocks(
                bA, bB, bc0, self.bound_spec.lo, self.bound_spec.hi, self.bound_spec.lo_t, self.bound_spec.hi_t,
                np.full(nb, s, dtype=np.int64), kb, self.bound_spec.order, n1, n2,
            )
        q = self.hull_of(s)
        f = poly.A.shape[0]
        w = self.problem.waypoints
        # P^1..P^4 depend on the start jet only, P^5..P^8 on the end jet only
        pa = poly.A
        # kron(X, A) written as a broadcast: np.kron is ~10x slower on these small blocks
        ca = (q[1:5, None, 1:5, None] * pa[None, :, None, :]).reshape(4 * f, 12)
        cb = (q[5:9, None, 6:10, None] * pa[None, :, None, :]).reshape(4 * f, 12)
        ca0 = (q[1:5, 0, None] * (pa @ w[s])[None, :]).ravel()
        cb0 = (q[5:9, 5, None] * (pa @ w[s + 1])[None, :]).ravel()
        cb_hi = np.tile(poly.b, 4)
        z = np.zeros((4 * f, 12))
        sl_a, sl_m, sl_b = slice(0, n1), slice(n1, n1 + n2), slice(n1 + n2, nb)
        A = np.vstack([bA[sl_a], ca, bA[sl_m], bA[sl_b], z])
        B = np.vstack([bB[sl_a], z, bB[sl_m], bB[sl_b], cb])
        c0 = np.concatenate([bc0[sl_a], ca0, bc0[sl_m], bc0[sl_b], cb0])
        neg = np.full(4 * f, -INF)
        hi_c = np.clip(cb_hi, -INF, INF)
        hi_ct = tighten(neg, hi_c)[1]

        def mix(bound: NDArray[Any], cor: NDArray[Any]) -> NDArray[Any]:
            return np.concatenate([bound[sl_a], cor, bound[sl_m], bound[sl_b], cor])

        kc = np.full(4 * f, KIND_CORRIDOR, dtype=np.int64)
        zc = np.zeros(4 * f, dtype=np.int64)
        return SegBlocks(
            A, B, c0, mix(self.bound_spec.lo, neg), mix(self.bound_spec.hi, hi_c), mix(self.bound_spec.lo_t, neg), mix(self.bound_spec.hi_t, hi_ct),
            np.full(nb + 8 * f, s, dtype=np.int64), mix(kb, kc), mix(self.bound_spec.order, zc), n1 + 4 * f, n2,
        )

    def _with_extra(self, blk: SegBlocks, s: int, extra: ExtraRows) -> SegBlocks:
        """`blk` with segment s's extra rows sum_i w_i (n . P^i) <= rhs (both jets: the middle group)."""
        sel = np.flatnonzero(extra.segment == s)
        if sel.size == 0:
            return blk
        g = extra.weights[sel] @ self.hull_of(s)[:10]  # (r, 10): over (side, order) of the jet pair
        n = extra.normal[sel]
        r = sel.size
        ea = (g[:, 1:5, None] * n[:, None, :]).reshape(r, 12)
        eb = (g[:, 6:10, None] * n[:, None, :]).reshape(r, 12)
        w = self.problem.waypoints
        e0 = g[:, 0] * (n @ w[s]) + g[:, 5] * (n @ w[s + 1])
        hi = np.clip(extra.rhs[sel], -INF, INF)
        neg = np.full(r, -INF)
        hi_t = tighten(neg, hi)[1]
        at = blk.n1 + blk.n2

        def ins(a: NDArray[Any], b: NDArray[Any]) -> NDArray[Any]:
            return np.concatenate([a[:at], b, a[at:]])

        return SegBlocks(
            ins(blk.A, ea), ins(blk.B, eb), ins(blk.c0, e0), ins(blk.lo, neg), ins(blk.hi, hi), ins(blk.lo_t, neg),
            ins(blk.hi_t, hi_t), ins(blk.seg, np.full(r, s, dtype=np.int64)),
            ins(blk.kind, np.full(r, KIND_CORRIDOR, dtype=np.int64)), ins(blk.order, np.zeros(r, dtype=np.int64)),
            blk.n1, blk.n2 + r,
        )

    def cost30(self, order: int, segments: Sequence[int] | None = None) -> FloatArray:
        """(S, 30, 30) per-segment cost matrices (times 2: the Hessian of z'Kz) in the 30-layout;
        with `segments`, (len(segments), 30, 30) of those, built for them alone unless every
        segment's are built (the general path's few segments: ~7 MB at m = 1000 otherwise)."""
        c = self._cost.get(order)
        if c is None and segments is not None:
            return _cost30(self.durations[np.asarray(segments, dtype=np.int64)], order)
        if c is None:
            c = self._cost[order] = _cost30(self.durations, order)
        return c if segments is None else c[np.asarray(segments, dtype=np.int64)]


class ExtraRows(Protocol):
    """Rows sum_i weights[r, i] (normal[r] . P[segment[r], i]) <= rhs[r] on control points."""

    @property
    def segment(self) -> NDArray[np.intp]: ...
    @property
    def weights(self) -> FloatArray: ...
    @property
    def normal(self) -> FloatArray: ...
    @property
    def rhs(self) -> FloatArray: ...


def _cost30(durations: FloatArray, order: int) -> FloatArray:
    k = cost_matrices(durations, order)
    return np.asarray(2.0 * np.einsum("sij,de->sidje", k, np.eye(3)).reshape(k.shape[0], 30, 30))


def tighten(lo: FloatArray, hi: FloatArray) -> tuple[FloatArray, FloatArray]:
    lo_t = np.where(lo > -INF, lo + MARGIN * (1.0 + np.abs(lo)), lo)
    hi_t = np.where(hi < INF, hi - MARGIN * (1.0 + np.abs(hi)), hi)
    return lo_t, hi_t
