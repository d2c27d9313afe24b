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

What is kept per problem (`ProblemCache`, its row blocks, `tighten`) is in
`planner_core.jets_cache`; this module assembles, solves and checks the QPs.
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from dataclasses import dataclass, field, replace
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from planner_core.bezier import segments_from_jets
from planner_core.constraints import INF, KIND_BOUND
from planner_core.jets_cache import BLOCKS_KEPT as BLOCKS_KEPT
from planner_core.jets_cache import MARGIN as MARGIN
from planner_core.jets_cache import (
    BoundRowSpec as BoundRowSpec,
)
from planner_core.jets_cache import (
    ExtraRows as ExtraRows,
)
from planner_core.jets_cache import ProblemCache, SegBlocks
from planner_core.jets_cache import tighten as tighten
from planner_core.problem import JET_ORDER, FloatArray, Problem, Trajectory
from planner_core.qp import QPResult, QPStatus, issparse, solve_qp

if TYPE_CHECKING:
    # imported where a sparse QP is built: ~0.1 s of start-up the dense per-window path never needs
    import scipy.sparse as sp

__all__ = ["JetSolve", "ProblemCache", "assemble", "initial_jets", "solve_jets", "trajectory_from_jets"]

COSTS = ("snap", "jerk", "waypoint-snap")
CHECK_TOL = 1e-9  # absolute: untightened rows must hold to this
WAYPOINT_SNAP_REG = 1e-6
NV = 4 * 3  # unknowns per free jet
DENSE_FALLBACK_JETS = 200  # up to 2400 unknowns, a dense solve is still affordable


def initial_jets(problem: Problem) -> FloatArray:
    """Jets array (m, 5, 3): terminal jets from the problem, interior at rest (placeholders)."""
    jets = np.zeros((problem.m, JET_ORDER, 3))
    jets[:, 0] = problem.waypoints
    jets[0] = problem.initial
    jets[-1] = problem.final
    return jets


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
