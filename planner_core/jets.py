"""The general jet solver every planner uses: solve the jets at `free` waypoints, others fixed.

`solve_jets(problem, jets, free, ...)` is the one primitive behind the
iterative pass (a receding window of free jets), the global QP (all interior
jets free) and local replanning (a handful of jets around a change):

- unknowns: velocity..snap (12 numbers) of each free jet; positions are the
  waypoints; every other jet is taken from `jets` as fixed;
- every segment touching a free jet is *fully* constrained: all hodograph
  control points (orders 1..4) within the bounds and control points P^1..P^8
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

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np
import scipy.sparse as sp
from numpy.typing import NDArray

from planner_core.bezier import segments_from_jets
from planner_core.constraints import (
    INF,
    KIND_BOUND,
    SegmentRows,
    cost_matrices,
    hull_maps,
    segment_rows,
)
from planner_core.problem import JET_ORDER, FloatArray, Problem, Trajectory
from planner_core.qp import QPResult, QPStatus, solve_qp

COSTS = ("snap", "jerk", "waypoint-snap")
MARGIN = 1e-6  # relative tightening of every limit
CHECK_TOL = 1e-9  # absolute: untightened rows must hold to this
WAYPOINT_SNAP_REG = 1e-6
NV = 4 * 3  # unknowns per free jet


def initial_jets(problem: Problem) -> FloatArray:
    """Jets array (m, 5, 3): terminal jets from the problem, interior at rest (placeholders)."""
    jets = np.zeros((problem.m, JET_ORDER, 3))
    jets[:, 0] = problem.waypoints
    jets[0] = problem.initial
    jets[-1] = problem.final
    return jets


class ProblemCache:
    """Everything that depends only on durations, bounds and corridors, built once per problem."""

    def __init__(self, problem: Problem) -> None:
        self.problem = problem
        self.durations = problem.durations
        self.hull = hull_maps(self.durations)
        self._rows: list[SegmentRows | None] = [None] * (problem.m - 1)
        self._tight: list[tuple[FloatArray, FloatArray] | None] = [None] * (problem.m - 1)
        self._cost: dict[int, FloatArray] = {}

    def rows(self, s: int) -> SegmentRows:
        r = self._rows[s]
        if r is None:
            b = self.problem.bounds
            r = segment_rows(self.hull[s], b.lo, b.hi, self.problem.corridor(s))
            self._rows[s] = r
        return r

    def tight(self, s: int) -> tuple[FloatArray, FloatArray]:
        t = self._tight[s]
        if t is None:
            r = self.rows(s)
            lo = np.where(r.lo > -INF, r.lo + MARGIN * (1.0 + np.abs(r.lo)), r.lo)
            hi = np.where(r.hi < INF, r.hi - MARGIN * (1.0 + np.abs(r.hi)), r.hi)
            t = (lo, hi)
            self._tight[s] = t
        return t

    def cost30(self, order: int) -> FloatArray:
        """(S, 30, 30) per-segment cost matrices in the 30-layout."""
        c = self._cost.get(order)
        if c is None:
            k = cost_matrices(self.durations, order)
            s = k.shape[0]
            c = np.einsum("sij,de->sidje", k, np.eye(3)).reshape(s, 30, 30)
            self._cost[order] = c
        return c


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
    problem = cache.problem
    m = problem.m
    free = sorted(free)
    if not free or free[0] < 1 or free[-1] > m - 2:
        raise ValueError(f"free: jets must be interior waypoints 1..{m - 2}, got {free}")
    pos = {f: i for i, f in enumerate(free)}
    nx = NV * len(free)
    full, half = _segment_roles(m, free, open_end)

    # constraint blocks: (row block coefficients per free jet, bounds, meta)
    g_blocks: list[tuple[int, int, FloatArray]] = []  # (row offset, jet position, (n, 12))
    lo_parts: list[FloatArray] = []
    hi_parts: list[FloatArray] = []
    lo0_parts: list[FloatArray] = []
    hi0_parts: list[FloatArray] = []
    meta: list[tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]] = []
    const_viol: list[tuple[int, int, int, float]] = []
    n_rows = 0
    for s in [*full, *([half] if half is not None else [])]:
        sr = cache.rows(s)
        tlo, thi = cache.tight(s)
        sel = sr.half if s == half else np.ones(sr.rows.shape[0], dtype=bool)
        if drop:
            for seg, kind, order in drop:
                if seg == s:
                    sel = sel & ~((sr.kind == kind) & (sr.order == order))
        R = sr.rows[sel]
        const = R[:, 0:3] @ jets[s, 0] + R[:, 15:18] @ jets[s + 1, 0]
        coeffs: list[tuple[int, FloatArray]] = []
        for side, jet in ((0, s), (1, s + 1)):
            block = R[:, 15 * side + 3 : 15 * side + 15]
            if jet in pos:
                coeffs.append((pos[jet], block))
            elif s != half or side == 0:
                const = const + block @ jets[jet, 1:].ravel()
        live = np.zeros(R.shape[0], dtype=bool)
        for _, block in coeffs:
            live |= np.any(block != 0.0, axis=1)
        lo0 = sr.lo[sel] - const
        hi0 = sr.hi[sel] - const
        dead = ~live
        if dead.any():
            viol = np.maximum(-hi0[dead], lo0[dead])  # 0 <= ... : constant value is 0 after shift
            kinds = sr.kind[sel][dead]
            orders = sr.order[sel][dead]
            for v, k, o in zip(viol, kinds, orders, strict=True):
                if v > CHECK_TOL:
                    const_viol.append((s, int(k), int(o), float(v)))
        n_live = int(live.sum())
        for p, block in coeffs:
            g_blocks.append((n_rows, p, block[live]))
        lo_parts.append((tlo[sel] - const)[live])
        hi_parts.append((thi[sel] - const)[live])
        lo0_parts.append(lo0[live])
        hi0_parts.append(hi0[live])
        meta.append((np.full(n_live, s), sr.kind[sel][live], sr.order[sel][live]))
        n_rows += n_live

    P, q = _cost_terms(cache, jets, free, pos, full, cost)
    G: FloatArray | sp.csc_matrix
    if sparse:
        rr: list[NDArray[np.int64]] = []
        cc: list[NDArray[np.int64]] = []
        vv: list[FloatArray] = []
        for r0, p, block in g_blocks:
            nz_r, nz_c = np.nonzero(block)
            rr.append(nz_r + r0)
            cc.append(nz_c + NV * p)
            vv.append(block[nz_r, nz_c])
        G = sp.csc_matrix(
            (np.concatenate(vv) if vv else np.zeros(0),
             (np.concatenate(rr) if rr else np.zeros(0, dtype=np.int64),
              np.concatenate(cc) if cc else np.zeros(0, dtype=np.int64))),
            shape=(n_rows, nx),
        )
    else:
        G = np.zeros((n_rows, nx))
        for r0, p, block in g_blocks:
            G[r0 : r0 + block.shape[0], NV * p : NV * p + NV] = block

    def cat(parts: list[FloatArray]) -> FloatArray:
        return np.concatenate(parts) if parts else np.zeros(0)

    return AssembledQP(
        P=sp.csc_matrix(P) if sparse else P,
        q=q,
        G=G,
        lo=cat(lo_parts),
        hi=cat(hi_parts),
        lo0=cat(lo0_parts),
        hi0=cat(hi0_parts),
        row_segment=np.concatenate([a for a, _, _ in meta]) if meta else np.zeros(0, dtype=np.int64),
        row_kind=np.concatenate([b for _, b, _ in meta]) if meta else np.zeros(0, dtype=np.int64),
        row_order=np.concatenate([c for _, _, c in meta]) if meta else np.zeros(0, dtype=np.int64),
        constant_violation=const_viol,
    )


def _cost_terms(
    cache: ProblemCache,
    jets: FloatArray,
    free: list[int],
    pos: dict[int, int],
    full: list[int],
    cost: str,
) -> tuple[FloatArray | sp.lil_matrix, FloatArray]:
    nx = NV * len(free)
    big = len(free) > 40
    P: FloatArray | sp.lil_matrix = sp.lil_matrix((nx, nx)) if big else np.zeros((nx, nx))
    q = np.zeros(nx)
    if cost == "waypoint-snap":
        snap_idx = np.concatenate([NV * p + np.arange(9, 12) for p in range(len(free))])
        diag = np.full(nx, WAYPOINT_SNAP_REG)
        diag[snap_idx] += 2.0
        if big:
            return sp.diags(diag).tolil(), q
        return np.diag(diag), q
    if cost not in ("snap", "jerk"):
        raise ValueError(f"cost: unknown cost {cost!r} (expected one of {COSTS})")
    k_all = cache.cost30(4 if cost == "snap" else 3)
    if big:
        return _cost_terms_sparse(k_all, jets, free, pos, full)
    assert isinstance(P, np.ndarray)
    for s in full:
        K = k_all[s]
        z = np.concatenate([jets[s].ravel(), jets[s + 1].ravel()])
        fixed = np.ones(30, dtype=bool)
        idx = []
        for side, jet in ((0, s), (1, s + 1)):
            if jet in pos:
                cols = np.arange(15 * side + 3, 15 * side + 15)
                fixed[cols] = False
                idx.append((pos[jet], cols))
        zf = np.where(fixed, z, 0.0)
        grad = 2.0 * K @ zf
        for pa, ca in idx:
            q[NV * pa : NV * pa + NV] += grad[ca]
            for pb, cb in idx:
                P[NV * pa : NV * pa + NV, NV * pb : NV * pb + NV] += 2.0 * K[np.ix_(ca, cb)]
    return P, q


def _cost_terms_sparse(
    k_all: FloatArray, jets: FloatArray, free: list[int], pos: dict[int, int], full: list[int]
) -> tuple[sp.coo_matrix, FloatArray]:
    nx = NV * len(free)
    q = np.zeros(nx)
    rows: list[NDArray[np.int64]] = []
    cols: list[NDArray[np.int64]] = []
    vals: list[FloatArray] = []
    local = np.arange(NV)
    for s in full:
        K = k_all[s]
        z = np.concatenate([jets[s].ravel(), jets[s + 1].ravel()])
        fixed = np.ones(30, dtype=bool)
        idx = []
        for side, jet in ((0, s), (1, s + 1)):
            if jet in pos:
                c = np.arange(15 * side + 3, 15 * side + 15)
                fixed[c] = False
                idx.append((pos[jet], c))
        grad = 2.0 * K @ np.where(fixed, z, 0.0)
        for pa, ca in idx:
            q[NV * pa : NV * pa + NV] += grad[ca]
            for pb, cb in idx:
                blk = 2.0 * K[np.ix_(ca, cb)]
                rows.append(np.repeat(NV * pa + local, NV))
                cols.append(np.tile(NV * pb + local, NV))
                vals.append(blk.ravel())
    P = sp.coo_matrix((np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(nx, nx))
    return P, q


def _column_scale(cache: ProblemCache, free: Sequence[int]) -> FloatArray:
    """Per-variable scale τ^k (τ: mean duration around the jet) so that derivative
    orders 1..4 have comparable magnitudes; without it long segments give Hessians
    with condition numbers ~ Δ^8."""
    d = cache.durations
    out = np.empty(NV * len(free))
    k = np.repeat(np.arange(1, 5), 3)
    for p, f in enumerate(sorted(free)):
        tau = 0.5 * (d[f - 1] + d[f])
        out[NV * p : NV * p + NV] = tau ** (-k.astype(float))
    return out


def solve_assembled(qp: AssembledQP, backend: str, col_scale: FloatArray | None = None) -> tuple[QPResult, float]:
    """Solve (on a row- and column-scaled copy) and check against the untightened rows.

    Returns (result, max violation of the untightened rows).
    """
    if qp.constant_violation:
        return QPResult(QPStatus.INFEASIBLE, None, 0, 0.0, backend), max(v for *_, v in qp.constant_violation)
    nx = qp.q.shape[0]
    c = np.ones(nx) if col_scale is None else col_scale
    if sp.issparse(qp.G):
        Gc = sp.csc_matrix(qp.G @ sp.diags(c))
        norms = np.sqrt(np.asarray(Gc.multiply(Gc).sum(axis=1)).ravel())
        norms[norms == 0] = 1.0
        Gs = sp.csc_matrix(sp.diags(1.0 / norms) @ Gc)
        Ps = sp.csc_matrix(sp.diags(c) @ sp.csc_matrix(qp.P) @ sp.diags(c))
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
    res = solve_qp(Ps / pscale, qp.q * c / pscale, Gs, lo, hi, backend)
    if not res.ok or res.x is None:
        return res, np.inf
    x = res.x * c
    r = np.asarray(qp.G @ x).ravel()
    viol = float(max(np.max(r - qp.hi0, initial=0.0), np.max(qp.lo0 - r, initial=0.0)))
    if viol > CHECK_TOL:
        return QPResult(QPStatus.FAILED, None, res.iterations, res.solve_time, backend), viol
    return replace(res, x=x), viol


def solve_jets(
    problem: Problem,
    jets: FloatArray,
    free: Sequence[int],
    *,
    cost: str = "snap",
    backend: str = "daqp",
    open_end: bool = False,
    cache: ProblemCache | None = None,
) -> JetSolve:
    """Solve the jets at `free` (interior indices) with every other jet of `jets` fixed.

    Returns a copy of `jets` with the free rows replaced (on success) and the
    QP's status. `cache` may be passed to reuse duration-dependent matrices
    across calls on the same problem.
    """
    cache = cache if cache is not None and cache.problem is problem else ProblemCache(problem)
    sparse = backend == "osqp" and len(free) > 4
    qp = assemble(cache, jets, free, cost=cost, open_end=open_end, sparse=sparse)
    res, viol = solve_assembled(qp, backend, _column_scale(cache, free))
    out = np.array(jets, dtype=float, copy=True)
    if res.ok and res.x is not None:
        out[sorted(free), 1:] = res.x.reshape(len(free), 4, 3)
    return JetSolve(res.status, out, res, viol, int(qp.G.shape[0]))


def trajectory_from_jets(problem: Problem, jets: FloatArray, stats: dict[str, object] | None = None) -> Trajectory:
    ctrl = segments_from_jets(jets, problem.durations)
    return Trajectory(problem.times.copy(), ctrl, problem.corridors, dict(stats or {}))


def group_name(segment: int, kind: int, order: int, n_segments: int) -> str:
    from planner_core.problem import ORDER_NAMES

    where = f"segment {segment}" + (" (terminal)" if segment == n_segments - 1 else "")
    if kind == KIND_BOUND:
        return f"bounds order {order} ({ORDER_NAMES[order]}) of {where}"
    return f"corridor of {where}"
