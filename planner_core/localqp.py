"""A dense QP over chosen entries of a few jets, every touched segment fully constrained.

Replanning and braking both fix most jets and free a few entries (the
derivative rows of the re-solved jets; the end position of a braking
segment). Every segment touching a free entry gets all its hull rows (bounds
of orders 1..4, corridor on P^1..P^8); rows that depend on fixed entries only
are checked instead of handed to the solver, so a fixed half that already
violates a (new) constraint is reported by name rather than as a bare
"infeasible". Cost: integrated squared snap over the touched segments.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from planner_core.bezier import hodograph_matrix, segment_from_jets
from planner_core.constraints import KIND_BOUND, cost_matrices, hull_maps, segment_rows
from planner_core.problem import DEGREE, JET_ORDER, ORDER_NAMES, Bounds, FloatArray, Polytope
from planner_core.qp import solve_qp

BoolArray = NDArray[np.bool_]
CorridorOf = Callable[[int], Polytope | None]

FIXED_TOL = 1e-9  # slack allowed on rows fixed by jets we do not re-solve (verify's tolerance)


@dataclass(frozen=True)
class LocalSolution:
    ok: bool
    jets: dict[int, FloatArray]  # the solved jets (only the ones with free entries)
    message: str
    qp_time: float
    n_vars: int
    n_rows: int


def _layout(free: Mapping[int, BoolArray]) -> tuple[dict[int, NDArray[np.int64]], int]:
    """Per jet, the variable index of each of its 15 entries (-1 when fixed)."""
    cols: dict[int, NDArray[np.int64]] = {}
    n = 0
    for j in sorted(free):
        mask = np.asarray(free[j], dtype=bool).ravel()
        idx = np.full(JET_ORDER * 3, -1, dtype=np.int64)
        k = int(mask.sum())
        idx[mask] = np.arange(n, n + k)
        cols[j] = idx
        n += k
    return cols, n


def _row_name(kind: int, order: int, segment: int) -> str:
    if kind == KIND_BOUND:
        return f"{ORDER_NAMES[order]} bound of segment {segment}"
    return f"corridor of segment {segment}"


def solve_local(
    jets: Mapping[int, FloatArray],
    durations: Mapping[int, float],
    bounds: Bounds,
    corridor_of: CorridorOf,
    segments: Sequence[int],
    free: Mapping[int, BoolArray],
    *,
    extra_cost: tuple[FloatArray, FloatArray] | None = None,
    extra_rows: tuple[FloatArray, FloatArray, FloatArray] | None = None,
    backend: str = "daqp",
) -> LocalSolution:
    """Choose the free entries of `jets` (segment s joins jets s and s+1).

    `jets` must hold both end jets of every segment in `segments` (free entries
    are used only as a fallback guess). `extra_cost` = (P, q) is added to the
    normalised snap cost, in variable space; `extra_rows` = (G, lo, hi) are
    more constraint rows in variable space (variables: the free entries of
    the free jets, jets in increasing index, entries row-major).
    """
    cols, n = _layout(free)
    if n == 0:
        return LocalSolution(True, {}, "nothing to solve", 0.0, 0, 0)
    blocks: list[FloatArray] = []
    los: list[FloatArray] = []
    his: list[FloatArray] = []
    P = np.zeros((n, n))
    q = np.zeros(n)
    none_free = np.full(JET_ORDER * 3, -1, dtype=np.int64)
    for s in segments:
        d = float(durations[s])
        hull = hull_maps(np.array([d]))[0]
        rows = segment_rows(hull, bounds.lo, bounds.hi, corridor_of(s))
        z = np.concatenate([jets[s].ravel(), jets[s + 1].ravel()])
        colmap = np.concatenate([cols.get(s, none_free), cols.get(s + 1, none_free)])
        fc = colmap >= 0
        rf = rows.rows[:, fc]
        const = rows.rows[:, ~fc] @ z[~fc]
        live = np.any(rf != 0.0, axis=1)
        dead = ~live
        bad = dead & ((const > rows.hi + FIXED_TOL) | (const < rows.lo - FIXED_TOL))
        if np.any(bad):
            r = int(np.flatnonzero(bad)[0])
            excess = float(max(const[r] - rows.hi[r], rows.lo[r] - const[r]))
            name = _row_name(int(rows.kind[r]), int(rows.order[r]), s)
            return LocalSolution(
                False, {}, f"{name} violated by {excess:.3g} by jets that are held fixed", 0.0, n, 0
            )
        g = np.zeros((int(live.sum()), n))
        g[:, colmap[fc]] = rf[live]
        blocks.append(g)
        los.append(rows.lo[live] - const[live])
        his.append(rows.hi[live] - const[live])
        k30 = np.kron(cost_matrices(np.array([d]), 4)[0], np.eye(3))
        ix = colmap[fc]
        P[np.ix_(ix, ix)] += k30[np.ix_(fc, fc)]
        q[ix] += k30[np.ix_(fc, ~fc)] @ z[~fc]
    scale = float(np.max(np.abs(np.diag(P))))
    scale = 1.0 if scale <= 0.0 else scale
    P = 2.0 * P / scale
    q = 2.0 * q / scale
    P += 1e-10 * np.eye(n)
    if extra_cost is not None:
        P += extra_cost[0]
        q += extra_cost[1]
    if extra_rows is not None:
        blocks.append(extra_rows[0])
        los.append(extra_rows[1])
        his.append(extra_rows[2])
    G = np.vstack(blocks) if blocks else np.zeros((0, n))
    lo = np.concatenate(los) if los else np.zeros(0)
    hi = np.concatenate(his) if his else np.zeros(0)
    t0 = time.perf_counter()
    if G.shape[0] == 0:
        x: FloatArray | None = np.asarray(np.linalg.solve(P, -q), dtype=np.float64)
        ok = True
    else:
        res = solve_qp(P, q, G, lo, hi, backend)
        x, ok = res.x, res.ok
    qp_time = time.perf_counter() - t0
    if not ok or x is None:
        where = ", ".join(str(j) for j in sorted(free))
        return LocalSolution(False, {}, f"QP infeasible for jets {where}", qp_time, n, G.shape[0])
    out: dict[int, FloatArray] = {}
    for j, idx in cols.items():
        jet = np.array(jets[j], dtype=float).ravel()
        m = idx >= 0
        jet[m] = x[idx[m]]
        out[j] = jet.reshape(JET_ORDER, 3)
    return LocalSolution(True, out, "ok", qp_time, n, G.shape[0])


@lru_cache(maxsize=4096)
def _hodograph_stack(d: float) -> FloatArray:
    """(30, 10): control points -> hodograph control points of orders 1..4, stacked."""
    out = np.vstack([hodograph_matrix(k, d) for k in range(1, 5)])
    out.setflags(write=False)
    return out


def hull_violation(
    ctrl: FloatArray,
    durations: FloatArray,
    bounds: Bounds,
    corridors: Sequence[Polytope | None],
    tol: float = 1e-9,
    labels: Sequence[int] | None = None,
) -> str | None:
    """First hull certificate failure of segments (s, 10, 3), or None when all pass.

    Checks every hodograph control point of orders 1..4 against the bounds and
    all 10 control points against the corridor. `labels` are the segments'
    indices to name in the message (default 0..s-1).
    """
    names = list(range(ctrl.shape[0])) if labels is None else list(labels)
    lo = bounds.lo[_ORDER_OF_ROW - 1]  # (30, 3)
    hi = bounds.hi[_ORDER_OF_ROW - 1]
    for i in range(ctrl.shape[0]):
        h = _hodograph_stack(float(durations[i])) @ ctrl[i]  # (30, 3)
        worst = np.maximum(h - hi, lo - h)
        if float(worst.max()) > tol:
            k = int(_ORDER_OF_ROW[int(np.argmax(worst.max(axis=1)))])
            return f"{ORDER_NAMES[k]} bound exceeded by {float(worst.max()):.3g} on segment {names[i]}"
        poly = corridors[i]
        if poly is not None and poly.A.shape[0] > 0:
            v = float((ctrl[i] @ poly.A.T - poly.b).max())
            if v > tol:
                return f"corridor violated by {v:.3g} on segment {names[i]}"
    return None


def build_segments(jets: Mapping[int, FloatArray], durations: Mapping[int, float], segments: Sequence[int]) -> FloatArray:
    """Control points (len(segments), 10, 3) of the given segments from their end jets."""
    return np.stack([segment_from_jets(jets[s], jets[s + 1], float(durations[s])) for s in segments])


# --- fast path: free jets' derivative rows (the replanning case) --------------

MARGIN = 1e-6  # relative tightening, as jets.py: the solution then meets the untightened rows
CHECK_TOL = 1e-9
_NV = 12  # velocity..snap x 3 axes per free jet


@lru_cache(maxsize=1)
def _jet_rows() -> tuple[FloatArray, FloatArray]:
    """(5, 5) maps from P^0..P^4 (resp. P^5..P^9) to the unscaled start (end) jet."""
    u0 = np.zeros((JET_ORDER, JET_ORDER))
    u1 = np.zeros((JET_ORDER, JET_ORDER))
    for k in range(JET_ORDER):
        h = hodograph_matrix(k, 1.0) if k else np.eye(DEGREE + 1)
        u0[k] = h[0, :JET_ORDER]
        u1[k] = h[-1, JET_ORDER:]
    u0.setflags(write=False)
    u1.setflags(write=False)
    return u0, u1


_POWERS = -np.arange(JET_ORDER, dtype=float)


def start_jet_fast(ctrl: FloatArray, duration: float) -> FloatArray:
    """bezier.start_jet without the per-order Python loop."""
    return np.asarray((_jet_rows()[0] @ ctrl[:JET_ORDER]) * (duration**_POWERS)[:, None])


def end_jet_fast(ctrl: FloatArray, duration: float) -> FloatArray:
    return np.asarray((_jet_rows()[1] @ ctrl[JET_ORDER:]) * (duration**_POWERS)[:, None])


def _tighten(lo: FloatArray, hi: FloatArray) -> tuple[FloatArray, FloatArray]:
    tlo = np.where(lo > -1e29, lo + MARGIN * (1.0 + np.abs(lo)), lo)
    thi = np.where(hi < 1e29, hi - MARGIN * (1.0 + np.abs(hi)), hi)
    return tlo, thi


@dataclass(frozen=True)
class _SegmentMats:
    """Everything about one segment's QP block that depends only on its duration and free sides."""

    Q: FloatArray  # (40, 10) hull map per axis over (side*5 + order)
    fixed: NDArray[np.bool_]  # (10,) entries held fixed
    live_b: NDArray[np.bool_]  # (30,) hodograph points that depend on a free entry
    order_live: NDArray[np.int64]  # bound row (order-1) of each live hodograph point
    order_dead: NDArray[np.int64]
    gb: dict[int, FloatArray]  # free side -> (3 * live points, 12) bound rows
    live_c: NDArray[np.bool_]  # (8,) control points P^1..P^8 that depend on a free entry
    qc: dict[int, FloatArray]  # free side -> (live points, 4) corridor coefficients per axis
    pblk: dict[tuple[int, int], FloatArray]  # (side a, side b) -> (12, 12) cost Hessian block
    kq: dict[int, FloatArray]  # free side -> (4, 10): cost gradient rows (times fixed entries)


_HODO = slice(DEGREE + 1, None)  # hull rows 10..39: hodographs of orders 1..4
_INNER = slice(1, DEGREE)  # control points P^1..P^8
_ORDER_OF_ROW = np.concatenate([np.full(DEGREE + 1 - k, k) for k in range(1, 5)])


def _expand(blk: FloatArray, other: FloatArray) -> FloatArray:
    """Rows (i, f) x columns (order, axis): blk[i, order] * other[f, axis]."""
    r, c = blk.shape
    f, a = other.shape
    return np.asarray((blk[:, None, :, None] * other[None, :, None, :]).reshape(r * f, c * a))


@lru_cache(maxsize=4096)
def _segment_mats(d: float, free0: bool, free1: bool) -> _SegmentMats:
    Q = hull_maps(np.array([d]))[0]
    K = cost_matrices(np.array([d]), 4)[0]
    sides = [side for side, f in ((0, free0), (1, free1)) if f]
    cols = {side: np.arange(side * JET_ORDER + 1, side * JET_ORDER + JET_ORDER) for side in sides}
    fixed = np.ones(2 * JET_ORDER, dtype=bool)
    for c in cols.values():
        fixed[c] = False
    qb = Q[_HODO]
    qi = Q[_INNER]
    live_b = np.zeros(qb.shape[0], dtype=bool)
    live_c = np.zeros(qi.shape[0], dtype=bool)
    for c in cols.values():
        live_b |= np.any(qb[:, c] != 0.0, axis=1)
        live_c |= np.any(qi[:, c] != 0.0, axis=1)
    eye3 = np.eye(3)
    return _SegmentMats(
        Q=Q,
        fixed=fixed,
        live_b=live_b,
        order_live=_ORDER_OF_ROW[live_b] - 1,
        order_dead=_ORDER_OF_ROW[~live_b] - 1,
        gb={side: _expand(qb[live_b][:, c], eye3) for side, c in cols.items()},
        live_c=live_c,
        qc={side: qi[live_c][:, c] for side, c in cols.items()},
        pblk={(sa, sb): 2.0 * _expand(K[np.ix_(ca, cb)], eye3) for sa, ca in cols.items() for sb, cb in cols.items()},
        kq={side: 2.0 * K[c] for side, c in cols.items()},
    )


def _solve_dense(
    P: FloatArray, q: FloatArray, G: FloatArray, lo: FloatArray, hi: FloatArray, backend: str
) -> tuple[FloatArray | None, str]:
    """daqp called directly on arrays built here (already contiguous float64, limits clipped):
    `solve_qp`'s conversions and result object cost as much as the solve at this size."""
    if backend != "daqp":
        res = solve_qp(P, q, G, lo, hi, backend)
        return (res.x if res.ok else None), res.status.value
    import daqp

    x, _, flag, _ = daqp.solve(P, q, G, hi, lo, np.zeros(lo.size, dtype=np.int32), primal_tol=1e-10, iter_limit=2000)
    if flag == 1 or flag == 2:
        return np.asarray(x, dtype=np.float64), "optimal"
    return None, "infeasible" if flag == -1 else "failed"


def solve_derivatives(
    jets: Mapping[int, FloatArray],
    durations: Mapping[int, float],
    bounds: Bounds,
    corridor_of: CorridorOf,
    free: Sequence[int],
    *,
    backend: str = "daqp",
) -> LocalSolution:
    """Velocity..snap of the `free` jets, all other jets fixed; every touching segment fully constrained.

    Same QP as jets.solve_jets (integrated squared snap, rows tightened by
    MARGIN, solution checked against the untightened rows), assembled per
    axis from per-duration cached blocks: it is the latency-critical step of
    a local replan.
    """
    free = sorted(free)
    pos = {j: i for i, j in enumerate(free)}
    n = _NV * len(free)
    segs = sorted({s for j in free for s in (j - 1, j)})
    g_parts: list[FloatArray] = []
    lo_parts: list[FloatArray] = []
    hi_parts: list[FloatArray] = []
    P = np.zeros((n, n))
    q = np.zeros(n)
    for s in segs:
        side_pos = {side: pos[j] for side, j in ((0, s), (1, s + 1)) if j in pos}
        mats = _segment_mats(float(durations[s]), 0 in side_pos, 1 in side_pos)
        Zf = np.concatenate([jets[s], jets[s + 1]]) * mats.fixed[:, None]  # (10, 3)
        base = mats.Q @ Zf  # every hull point's value from the fixed entries
        vb = base[_HODO]
        live = mats.live_b
        vdead = vb[~live]
        over = np.maximum(vdead - bounds.hi[mats.order_dead], bounds.lo[mats.order_dead] - vdead)
        if over.size and float(over.max()) > CHECK_TOL:
            k = int(mats.order_dead[int(np.argmax(over.max(axis=1)))]) + 1
            return LocalSolution(False, {}, f"{ORDER_NAMES[k]} bound of segment {s} violated by "
                                 f"{float(over.max()):.3g} by jets held fixed", 0.0, n, 0)
        vlive = vb[live]
        g = np.zeros((vlive.size, n))
        for side, p in side_pos.items():
            g[:, _NV * p : _NV * p + _NV] = mats.gb[side]
        g_parts.append(g)
        lo_parts.append((bounds.lo[mats.order_live] - vlive).ravel())
        hi_parts.append((bounds.hi[mats.order_live] - vlive).ravel())
        poly = corridor_of(s)
        if poly is not None and poly.A.shape[0]:
            vc = base[_INNER] @ poly.A.T - poly.b  # (8, faces): <= 0 wanted
            lc = mats.live_c
            if not lc.all() and float(vc[~lc].max()) > CHECK_TOL:
                return LocalSolution(False, {}, f"corridor of segment {s} violated by "
                                     f"{float(vc[~lc].max()):.3g} by jets held fixed", 0.0, n, 0)
            gc = np.zeros((int(lc.sum()) * poly.A.shape[0], n))
            for side, p in side_pos.items():
                gc[:, _NV * p : _NV * p + _NV] = _expand(mats.qc[side], poly.A)
            g_parts.append(gc)
            lo_parts.append(np.full(gc.shape[0], -1e30))
            hi_parts.append(-vc[lc].ravel())
        for sa, pa in side_pos.items():
            q[_NV * pa : _NV * pa + _NV] += (mats.kq[sa] @ Zf).ravel()
            for sb, pb in side_pos.items():
                P[_NV * pa : _NV * pa + _NV, _NV * pb : _NV * pb + _NV] += mats.pblk[(sa, sb)]
    G = np.vstack(g_parts)
    lo0 = np.clip(np.concatenate(lo_parts), -1e30, 1e30)
    hi0 = np.clip(np.concatenate(hi_parts), -1e30, 1e30)
    lo_t, hi_t = _tighten(lo0, hi0)
    t0 = time.perf_counter()
    x, status = _solve_dense(P, q, G, lo_t, hi_t, backend)
    qp_time = time.perf_counter() - t0
    if x is None:
        return LocalSolution(False, {}, f"QP {status} for jets {free}", qp_time, n, G.shape[0])
    rv = G @ x
    viol = float(max(np.max(rv - hi0, initial=0.0), np.max(lo0 - rv, initial=0.0)))
    if viol > CHECK_TOL:
        return LocalSolution(False, {}, f"QP solution misses a row by {viol:.3g} for jets {free}", qp_time, n, G.shape[0])
    out: dict[int, FloatArray] = {}
    for j, p in pos.items():
        jet = np.array(jets[j], dtype=float)
        jet[1:] = x[_NV * p : _NV * p + _NV].reshape(4, 3)
        out[j] = jet
    return LocalSolution(True, out, "ok", qp_time, n, G.shape[0])
