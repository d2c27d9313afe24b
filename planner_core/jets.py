"""The general jet solver every planner uses: solve the jets at `free` waypoints, others fixed.

`solve_jets(problem, jets, free, ...)` is the one primitive behind the
iterative pass (a receding window of free jets), the global QP (all interior
jets free) and local replanning (a handful of jets around a change):

- unknowns: velocity..snap (12 numbers) of each free jet; positions are the
  waypoints; every other jet is taken from `jets` as fixed;
- every segment touching a free jet is *fully* constrained: all hodograph
  control points (orders 1..4, on `constraints.HULL_PIECES` de Casteljau pieces) within
  the bounds and control points P^1..P^8
  inside its corridor (P^0, P^9 are the waypoints, checked by the loader);
- with `open_end=True` the jet after the last free one is not yet decided, so
  the segment after the window is *half* constrained: P^1..P^4 and the
  hodograph points that depend only on them (i + k <= 4); it is not in the
  cost. If that segment is the last one (its end jet is the terminal jet) it
  is fully constrained instead;
- cost: "snap" (default) = integrated squared snap over the fully constrained
  segments; "jerk" likewise; "waypoint-snap" (paper eq. 15) = squared snap at
  the free waypoints, rank-deficient, so a 1e-6 identity regulariser is added;
- constraints are tightened by `MARGIN` (relative) so that the returned
  solution satisfies the untightened ones exactly; every solution is checked
  against the untightened rows before it is returned.

A replanner calls it as:
    res = solve_jets(problem, traj_jets, [j - 1, j, j + 1])
    if res.ok: new_jets = res.jets   # every non-free jet is bit-for-bit unchanged
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property
from typing import TYPE_CHECKING, Any, Protocol

import numpy as np
from numpy.typing import NDArray

from planner_core.bezier import segments_from_jets
from planner_core.constraints import (
    INF,
    KIND_BOUND,
    KIND_CORRIDOR,
    SegmentRows,
    cost_matrices,
    hull_maps,
    segment_rows,
)

__all__ = ["JetSolve", "ProblemCache", "assemble", "initial_jets", "solve_jets", "trajectory_from_jets"]
from planner_core.problem import JET_ORDER, FloatArray, Problem, Trajectory
from planner_core.qp import QPResult, QPStatus, issparse, solve_qp

if TYPE_CHECKING:
    # imported where a sparse QP is built: ~0.1 s of start-up the dense per-window path never needs
    import scipy.sparse as sp

COSTS = ("snap", "jerk", "waypoint-snap")
MARGIN = 1e-6  # relative tightening of every limit
CHECK_TOL = 1e-9  # absolute: untightened rows must hold to this
WAYPOINT_SNAP_REG = 1e-6
NV = 4 * 3  # unknowns per free jet
BLOCKS_KEPT = 64  # segments whose row blocks a ProblemCache keeps (a window touches ~10)
DENSE_FALLBACK_JETS = 200  # up to 2400 unknowns, a dense solve is still affordable


def initial_jets(problem: Problem) -> FloatArray:
    """Jets array (m, 5, 3): terminal jets from the problem, interior at rest (placeholders)."""
    jets = np.zeros((problem.m, JET_ORDER, 3))
    jets[:, 0] = problem.waypoints
    jets[0] = problem.initial
    jets[-1] = problem.final
    return jets


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


@dataclass
class AssembledQP:
    """One QP in the free-jet variables, with per-row metadata for diagnosis."""

    P: FloatArray | sp.csc_matrix
    q: FloatArray
    G: FloatArray | sp.csc_matrix
    lo: FloatArray  # tightened
    hi: FloatArray
    lo0: FloatArray  # untightened, for the exactness check
    hi0: FloatArray
    row_segment: NDArray[np.int64]
    row_kind: NDArray[np.int64]
    row_order: NDArray[np.int64]
    constant_violation: list[tuple[int, int, int, float]] = field(default_factory=list)


@dataclass(frozen=True)
class JetSolve:
    status: QPStatus
    jets: FloatArray  # (m, 5, 3); equals the input where not free / not solved
    qp: QPResult | None
    max_violation: float
    n_rows: int
    t_build: float = 0.0  # seconds: assembling the QP from cached rows
    t_solve: float = 0.0  # seconds: backend call(s)
    t_check: float = 0.0  # seconds: scaling, row selection, exactness check
    n_active_rows: int = 0  # rows handed to the backend (lazy selection)

    @property
    def ok(self) -> bool:
        return self.status is QPStatus.OPTIMAL


def _segment_roles(m: int, free: Sequence[int], open_end: bool) -> tuple[list[int], int | None]:
    n_seg = m - 1
    segs = sorted({s for f in free for s in (f - 1, f) if 0 <= s < n_seg})
    half: int | None = None
    last = max(free)
    if open_end and last < n_seg - 1:
        half = last
        segs.remove(last)
    return segs, half


def assemble(
    cache: ProblemCache,
    jets: FloatArray,
    free: Sequence[int],
    *,
    cost: str = "snap",
    open_end: bool = False,
    sparse: bool = False,
    drop: frozenset[tuple[int, int, int]] = frozenset(),
) -> AssembledQP:
    """Build the QP for `free` jets. `drop` removes groups (segment, kind, order) for diagnosis."""
    m = cache.problem.m
    free = sorted(free)
    if not free or free[0] < 1 or free[-1] > m - 2:
        raise ValueError(f"free: jets must be interior waypoints 1..{m - 2}, got {free}")
    pos = {f: i for i, f in enumerate(free)}
    nx = NV * len(free)
    full, half = _segment_roles(m, free, open_end)

    g_blocks: list[tuple[int, int, FloatArray]] = []  # (row offset, jet position, (n, 12))
    lim_p: list[FloatArray] = []
    meta_p: list[NDArray[np.int64]] = []
    const_viol: list[tuple[int, int, int, float]] = []
    n_rows = 0
    segs = [*full, *([half] if half is not None else [])]
    for s in segs:
        a_free = s in pos
        b_free = (s + 1) in pos and s != half
        role = "half" if s == half else ("ab" if a_free and b_free else ("a" if a_free else "b"))
        blk = cache.blocks(s)
        if role in ("a", "b"):
            _check_constant_rows(blk, s, blk.dead(role), jets, const_viol)
        sl = blk.role(role)
        A, B, c0, lim, meta = blk.A[sl], blk.B[sl], blk.c0[sl], blk.lim[:, sl], blk.meta[:, sl]
        if drop:
            keep = np.ones(meta.shape[1], dtype=bool)
            for dseg, dkind, dorder in drop:
                if dseg == s:
                    keep &= ~((meta[1] == dkind) & (meta[2] == dorder))
            A, B, c0, lim, meta = A[keep], B[keep], c0[keep], lim[:, keep], meta[:, keep]
        const = c0
        if a_free:
            g_blocks.append((n_rows, pos[s], A))
        else:
            const = const + A @ jets[s, 1:].ravel()
        if b_free:
            g_blocks.append((n_rows, pos[s + 1], B))
        elif role != "half":
            const = const + B @ jets[s + 1, 1:].ravel()
        lim_p.append(lim - const)
        meta_p.append(meta)
        n_rows += meta.shape[1]

    P, q = _cost_terms(cache, jets, free, pos, full, cost, sparse)
    G: FloatArray | sp.csc_matrix
    if sparse:
        G = _sparse_rows(g_blocks, n_rows, nx)
    else:
        G = np.zeros((n_rows, nx))
        for r0, p, block in g_blocks:
            G[r0 : r0 + block.shape[0], NV * p : NV * p + NV] = block
    L = np.concatenate(lim_p, axis=1)
    M = np.concatenate(meta_p, axis=1)
    return AssembledQP(P, q, G, L[0], L[1], L[2], L[3], M[0], M[1], M[2], const_viol)


def _check_constant_rows(
    blk: SegBlocks, s: int, dead: slice, jets: FloatArray, out: list[tuple[int, int, int, float]]
) -> None:
    """Rows of a segment that involve only its fixed jet are constants: they must already hold."""
    if dead.stop <= dead.start:
        return
    val = blk.c0[dead] + blk.A[dead] @ jets[s, 1:].ravel() + blk.B[dead] @ jets[s + 1, 1:].ravel()
    viol = np.maximum(val - blk.hi[dead], blk.lo[dead] - val)
    if viol.max() > CHECK_TOL:
        for i in np.flatnonzero(viol > CHECK_TOL):
            out.append((s, int(blk.kind[dead][i]), int(blk.order[dead][i]), float(viol[i])))


def _sparse_rows(g_blocks: list[tuple[int, int, FloatArray]], n_rows: int, nx: int) -> sp.csc_matrix:
    import scipy.sparse as sp

    rr: list[NDArray[np.int64]] = []
    cc: list[NDArray[np.int64]] = []
    vv: list[FloatArray] = []
    for r0, p, block in g_blocks:
        nz_r, nz_c = np.nonzero(block)
        rr.append(nz_r + r0)
        cc.append(nz_c + NV * p)
        vv.append(block[nz_r, nz_c])
    if not vv:
        return sp.csc_matrix((n_rows, nx))
    return sp.csc_matrix((np.concatenate(vv), (np.concatenate(rr), np.concatenate(cc))), shape=(n_rows, nx))


_SIDE = (slice(3, 15), slice(18, 30))


def _cost_terms(
    cache: ProblemCache,
    jets: FloatArray,
    free: list[int],
    pos: dict[int, int],
    full: list[int],
    cost: str,
    sparse: bool,
) -> tuple[FloatArray | sp.csc_matrix, FloatArray]:
    if sparse:
        import scipy.sparse as sp
    nx = NV * len(free)
    q = np.zeros(nx)
    if cost == "waypoint-snap":
        diag = np.full(nx, WAYPOINT_SNAP_REG)
        for p in range(len(free)):
            diag[NV * p + 9 : NV * p + 12] += 2.0
        return (sp.diags(diag, format="csc") if sparse else np.diag(diag)), q
    if cost not in ("snap", "jerk"):
        raise ValueError(f"cost: unknown cost {cost!r} (expected one of {COSTS})")
    segs = list(full)
    k_segs = cache.cost30(4 if cost == "snap" else 3, segs)
    blocks: list[tuple[int, int, FloatArray]] = []
    for s, K in zip(segs, k_segs, strict=True):
        pa = pos.get(s)
        pb = pos.get(s + 1)
        if pa is not None and pb is not None:
            blocks += [(pa, pa, K[3:15, 3:15]), (pa, pb, K[3:15, 18:30]), (pb, pa, K[18:30, 3:15]),
                       (pb, pb, K[18:30, 18:30])]
            # only the (fixed) positions enter the linear term
            grad = K[:, [0, 1, 2, 15, 16, 17]] @ np.concatenate([jets[s, 0], jets[s + 1, 0]])
            q[NV * pa : NV * pa + NV] += grad[3:15]
            q[NV * pb : NV * pb + NV] += grad[18:30]
        elif pa is not None:
            blocks.append((pa, pa, K[3:15, 3:15]))
            z = np.concatenate([jets[s, 0], np.zeros(NV), jets[s + 1].ravel()])
            q[NV * pa : NV * pa + NV] += K[3:15] @ z
        elif pb is not None:
            blocks.append((pb, pb, K[18:30, 18:30]))
            z = np.concatenate([jets[s].ravel(), jets[s + 1, 0], np.zeros(NV)])
            q[NV * pb : NV * pb + NV] += K[18:30] @ z
    if sparse:
        local = np.arange(NV)
        rows = [np.repeat(NV * pa + local, NV) for pa, _, _ in blocks]
        cols = [np.tile(NV * pb + local, NV) for _, pb, _ in blocks]
        vals = [blk.ravel() for _, _, blk in blocks]
        P = sp.csc_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(nx, nx))
        return P, q
    Pd = np.zeros((nx, nx))
    for pa, pb, blk in blocks:
        Pd[NV * pa : NV * pa + NV, NV * pb : NV * pb + NV] += blk
    return Pd, q


def _column_scale(cache: ProblemCache, free: Sequence[int]) -> FloatArray:
    """Per-variable scale τ^-k (τ: mean duration around the jet) so that derivative
    orders 1..4 have comparable magnitudes; without it long segments give Hessians
    with condition numbers ~ Δ^8."""
    d = cache.durations
    f = np.asarray(sorted(free))
    tau = 0.5 * (d[f - 1] + d[f])
    return np.asarray((tau[:, None] ** -_ORDERS[None, :]).ravel())


_ORDERS = np.repeat(np.arange(1, 5), 3).astype(float)
LAZY_SLACK = 0.2  # rows whose relative slack at the guess is below this start in the working set
LAZY_ROUNDS = 6
LAZY = True
LAZY_MIN_VARS = 36  # measured: below 3 jets the selection costs more than it saves


def solve_assembled(
    qp: AssembledQP,
    backend: str,
    col_scale: FloatArray | None = None,
    guess: FloatArray | None = None,
) -> tuple[QPResult, float, int]:
    """Solve (on a row- and column-scaled copy) and check against the untightened rows.

    With `guess` (dense backends only), start from the rows that are nearly
    active at the guess and add violated rows until none is left: the result
    is then optimal for the full QP (optimal on a relaxation, feasible for all).
    Returns (result, max violation of the untightened rows, rows given to the backend).
    """
    if qp.constant_violation:
        res = QPResult(QPStatus.INFEASIBLE, None, 0, 0.0, backend)
        return res, max(v for *_, v in qp.constant_violation), 0
    nx = qp.q.shape[0]
    if backend == "osqp":
        # OSQP's own Ruiz equilibration does better without ours (measured: 950 vs 20000 iterations)
        res = solve_qp(qp.P, qp.q, qp.G, qp.lo, qp.hi, backend)
        if not res.ok:
            return res, np.inf, qp.lo.size
        return _checked(qp, res, backend, np.ones(nx), qp.lo.size)
    c = np.ones(nx) if col_scale is None else col_scale
    if issparse(qp.G):
        import scipy.sparse as sp

        Gc = sp.csc_matrix(qp.G @ sp.diags(c))
        norms = np.sqrt(np.asarray(Gc.multiply(Gc).sum(axis=1)).ravel())
        norms[norms == 0] = 1.0
        Gs: FloatArray | sp.csc_matrix = sp.csc_matrix(sp.diags(1.0 / norms) @ Gc)
        Ps: FloatArray | sp.csc_matrix = sp.csc_matrix(sp.diags(c) @ sp.csc_matrix(qp.P) @ sp.diags(c))
        pscale = float(np.max(np.abs(Ps.diagonal()))) or 1.0
    else:
        Gc = np.asarray(qp.G) * c[None, :]
        norms = np.linalg.norm(Gc, axis=1)
        norms[norms == 0] = 1.0
        Gs = Gc / norms[:, None]
        Ps = np.asarray(qp.P) * np.outer(c, c)
        pscale = float(np.max(np.abs(np.diag(Ps)))) or 1.0
    lo = np.where(qp.lo > -INF, qp.lo / norms, -INF)
    hi = np.where(qp.hi < INF, qp.hi / norms, INF)
    Ps = Ps / pscale
    qs = qp.q * c / pscale
    n_used = lo.size
    if LAZY and guess is not None and not issparse(Gs) and nx >= LAZY_MIN_VARS and lo.size > 2 * nx:
        res, n_used = _solve_lazy(Ps, qs, np.asarray(Gs), lo, hi, guess / c, backend)
    else:
        res = solve_qp(Ps, qs, Gs, lo, hi, backend)
    if not res.ok or res.x is None:
        return res, np.inf, n_used
    return _checked(qp, res, backend, c, n_used)


def _checked(qp: AssembledQP, res: QPResult, backend: str, c: FloatArray, n_used: int) -> tuple[QPResult, float, int]:
    assert res.x is not None
    x = res.x * c
    r = np.asarray(qp.G @ x).ravel()
    viol = float(max(np.max(r - qp.hi0, initial=0.0), np.max(qp.lo0 - r, initial=0.0)))
    if viol > CHECK_TOL:
        return QPResult(QPStatus.FAILED, None, res.iterations, res.solve_time, backend), viol, n_used
    return replace(res, x=x), viol, n_used


def _solve_lazy(
    P: FloatArray, q: FloatArray, G: FloatArray, lo: FloatArray, hi: FloatArray, y0: FloatArray, backend: str
) -> tuple[QPResult, int]:
    r = G @ y0
    span = np.minimum(hi - r, r - lo)
    scale = 1.0 + np.minimum(np.abs(hi), np.abs(lo))
    work = span < LAZY_SLACK * scale
    total = 0.0
    iters = 0
    for _ in range(LAZY_ROUNDS):
        idx = np.flatnonzero(work)
        res = solve_qp(P, q, G[idx], lo[idx], hi[idx], backend)
        total += res.solve_time
        iters += res.iterations
        if not res.ok or res.x is None:
            return replace(res, solve_time=total, iterations=iters), int(idx.size)
        r = G @ res.x
        tol = 1e-12 * (1.0 + np.abs(hi))
        bad = ((r > hi + tol) | (r < lo - tol)) & ~work
        if not bad.any():
            return replace(res, solve_time=total, iterations=iters), int(idx.size)
        work |= bad
    res = solve_qp(P, q, G, lo, hi, backend)
    return replace(res, solve_time=total + res.solve_time, iterations=iters + res.iterations), int(lo.size)


def solve_jets(
    problem: Problem,
    jets: FloatArray,
    free: Sequence[int],
    *,
    cost: str = "snap",
    backend: str = "daqp",
    open_end: bool = False,
    cache: ProblemCache | None = None,
    guess: FloatArray | None = None,
) -> JetSolve:
    """Solve the jets at `free` (interior indices) with every other jet of `jets` fixed.

    Returns a copy of `jets` with the free rows replaced (on success) and the
    QP's status. `cache` may be passed to reuse duration-dependent matrices
    across calls on the same problem. `guess` (m, 5, 3), e.g. the previous
    window's solution, lets the dense backend start from the nearly active rows.
    """
    cache = cache if cache is not None and cache.problem is problem else ProblemCache(problem)
    sparse = backend == "osqp" and len(free) > 4
    t0 = time.perf_counter()
    qp = assemble(cache, jets, free, cost=cost, open_end=open_end, sparse=sparse)
    t1 = time.perf_counter()
    x0 = None if guess is None else np.asarray(guess)[sorted(free), 1:].ravel()
    res, viol, n_used = solve_assembled(qp, backend, _column_scale(cache, free), x0)
    if res.status is QPStatus.FAILED and backend == "osqp" and len(free) <= DENSE_FALLBACK_JETS:
        # ADMM stalled or its answer did not refine to an exact one: the dense active-set solver is exact
        qp = assemble(cache, jets, free, cost=cost, open_end=open_end)
        res, viol, n_used = solve_assembled(qp, "daqp", _column_scale(cache, free), None)
    t2 = time.perf_counter()
    out = np.array(jets, dtype=float, copy=True)
    if res.ok and res.x is not None:
        out[sorted(free), 1:] = res.x.reshape(len(free), 4, 3)
    t_solve = res.solve_time if res.solve_time > 0 else t2 - t1
    return JetSolve(
        res.status, out, res, viol, int(qp.G.shape[0]), t1 - t0, t_solve, max(t2 - t1 - t_solve, 0.0), n_used
    )


def trajectory_from_jets(problem: Problem, jets: FloatArray, stats: dict[str, object] | None = None) -> Trajectory:
    ctrl = segments_from_jets(jets, problem.durations)
    return Trajectory(problem.times.copy(), ctrl, problem.corridors, dict(stats or {}))


def group_name(segment: int, kind: int, order: int, n_segments: int) -> str:
    from planner_core.problem import ORDER_NAMES

    where = f"segment {segment}" + (" (terminal)" if segment == n_segments - 1 else "")
    if kind == KIND_BOUND:
        return f"bounds order {order} ({ORDER_NAMES[order]}) of {where}"
    return f"corridor of {where}"
