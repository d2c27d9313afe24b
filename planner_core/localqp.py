"""A dense QP over chosen entries of a few jets, every touched segment fully constrained.

Replanning and braking both fix most jets and free a few entries (the
derivative rows of the re-solved jets; the end position of a braking
segment). Every segment touching a free entry gets all its hull rows (bounds
of orders 1..4, corridor on P^1..P^8); rows that depend on fixed entries only
are checked instead of handed to the solver, so a fixed half that already
violates a (new) constraint is reported by name rather than as a bare
"infeasible". Cost: integrated squared snap over the touched segments.

`solve_derivatives` (a local replan's QP) and `certificate.certify_rebuilt`
(its certificate) are the latency-critical path: everything that depends only on
durations, free-jet pattern, face counts or bounds is built once and cached
(read-only arrays), so a call is a few batched numpy products and one daqp solve. Those
caches live in `planner_core.localqp_structure`; this module holds the general `solve_local`
and the per-call work of `solve_derivatives`.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from numpy.typing import NDArray

from planner_core.certificate import (
    HODO_ROWS,
    ORDER_OF_ROW,
    hodograph_limits,
)
from planner_core.constraints import (
    KIND_BOUND,
    cost_matrices,
    hull_maps,
    segment_rows,
)
from planner_core.localqp_structure import (
    NV,
    bound_limits,
    bounds_key,
    expand,
    norm_limits,
    norm_structure,
    qp_structure,
    segment_mats,
)
from planner_core.problem import (
    DEGREE,
    JET_ORDER,
    ORDER_NAMES,
    Bounds,
    FloatArray,
    Polytope,
)
from planner_core.qp import DaqpSolver, solve_qp

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
        rows = segment_rows(hull, bounds, corridor_of(s))
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


# --- fast path: free jets' derivative rows (the replanning case) --------------

MARGIN = 1e-6  # relative tightening, as jets.py: the solution then meets the untightened rows
CHECK_TOL = 1e-9
_INF = 1e30  # both QP backends' "no bound"
_SIGN = np.array([[1.0], [-1.0]])  # row 0 lower limits, row 1 upper limits


def _solve_dense(
    P: FloatArray, q: FloatArray, G: FloatArray, lo: FloatArray, hi: FloatArray, backend: str
) -> tuple[FloatArray | None, str]:
    """daqp's reusable handle on arrays built here (already contiguous float64, limits clipped):
    `solve_qp`'s conversions and result object cost as much as the solve at this size."""
    if backend != "daqp":
        res = solve_qp(P, q, G, lo, hi, backend)
        return (res.x if res.ok else None), res.status.value
    sol = _dense_solver().solve(P, q, G, hi, lo, np.zeros(lo.size, dtype=np.int32))
    if sol.ok:
        return np.asarray(sol.x, dtype=np.float64), sol.status.value
    return None, sol.status.value


@lru_cache(maxsize=1)
def _dense_solver() -> DaqpSolver:
    return DaqpSolver(primal_tol=1e-10, iter_limit=2000)


_MARGIN_SIGN = MARGIN * _SIGN


def _tightened(lim: FloatArray, n_bound: int, infinite: NDArray[np.bool_] | None) -> FloatArray:
    """The QP's limits (2, rows) moved inwards by MARGIN * (1 + |limit|), so that the solution
    meets the untightened rows; rows without a limit (corridor lower limits, infinite
    bounds) stay at +-_INF."""
    t = np.abs(lim)
    t += 1.0
    t *= _MARGIN_SIGN
    t += lim
    t[0, n_bound:] = -_INF
    if infinite is not None:
        np.copyto(t[:, :n_bound], lim[:, :n_bound], where=infinite)
    return t


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
    MARGIN, solution checked against the untightened rows). It is the
    latency-critical step of a local replan: everything that depends only on
    durations, face counts and bounds comes from caches (`qp_structure`,
    `bound_limits`); per call, a few products give the fixed jets' part, then
    the corridor rows and the solve. Rows that depend on fixed entries only are
    checked with the solution, not solved; a violated one is named (`_fixed_failure`).
    """
    free = sorted(free)
    pos = {j: i for i, j in enumerate(free)}
    segs = sorted({s for j in free for s in (j - 1, j)})
    s0 = segs[0]
    polys = [corridor_of(s) for s in segs]
    faces = [0 if p is None else int(p.A.shape[0]) for p in polys]
    pat_key = tuple((s - s0, pos.get(s, -1), pos.get(s + 1, -1), f) for s, f in zip(segs, faces, strict=True))
    ds_key = tuple(float(durations[s]) for s in segs)
    st = qp_structure(len(free), pat_key, ds_key)
    pt = st.pat
    n, k, nb, nl = pt.n, len(segs), pt.n_bound, pt.n_live
    limits, finite = bound_limits(bounds_key(bounds), k)
    J = np.array([jets[s0 + o] for o in pt.jets]).reshape(-1, 3)  # (5 nj, 3)
    values = st.hodo.dot(J).reshape(-1)  # every certified hodograph value (point-major, then axis)
    room = limits - values  # (2, 3 n k): limit - value of every hodograph point
    vi = st.inner.dot(J)  # (9 k, 3): P^0..P^8 of every segment from the fixed entries
    G = st.G.copy()
    if pt.uniform_col is not None and st.uniform_qc is not None:  # one free side per segment, one face count
        col, cq = pt.uniform_col, st.uniform_qc
        present = [p for p in polys if p is not None]  # all of them, as the pattern says
        A = np.array([p.A for p in present])  # (k, F, 3)
        vc = (vi.reshape(k, DEGREE, 3) @ A.transpose(0, 2, 1) - np.array([p.b for p in present])[:, None, :]).ravel()
        expanded = cq[:, :, None, :, None] * A[:, None, :, None, :]  # (k, points, F, 4, 3)
        G[nb:nl, col : col + NV] = expanded.reshape(-1, NV)
    else:
        vc = np.empty(pt.face_off[-1] + DEGREE * faces[-1])
        for i, poly in enumerate(polys):
            if faces[i] and poly is not None:
                o = pt.face_off[i]
                vc[o : o + DEGREE * faces[i]] = (vi[DEGREE * i : DEGREE * (i + 1)].dot(poly.A.T) - poly.b).ravel()
        for (i, r0, col, _), qc in zip(pt.corridor_blocks, st.qc, strict=True):
            poly = polys[i]
            assert poly is not None  # blocks exist only for segments with faces
            G[r0 : r0 + qc.shape[0] * faces[i], col : col + NV] = expand(qc, poly.A)
    lim = np.empty((2, pt.n_rows))  # lower, upper
    lim[:, :nb] = room[:, pt.live_b]
    lim[0, nb:nl] = -_INF
    lim[1, nb:nl] = -vc[pt.live_c]
    dc = nl + pt.n_dead_bound
    lim[:, nl:dc] = room[:, pt.dead_b]
    lim[0, dc:] = -_INF
    lim[1, dc:] = -vc[pt.dead_c]
    infinite = None
    if not finite:
        np.minimum(lim, _INF, out=lim)
        np.maximum(lim, -_INF, out=lim)
        infinite = np.abs(lim[:, :nb]) >= _INF
    tight = _tightened(lim[:, :nl], nb, infinite)
    q = st.grad.dot(J).ravel()
    Gs = G[:nl]
    norm = None
    if bounds.has_norm:
        nr = norm_structure(len(free), pat_key, ds_key, tuple(bool(v) for v in np.isfinite(bounds.horizontal)),
                             bounds.sides)
        limn = norm_limits(nr, bounds, values)
        live = nr.live
        dead_v = (limn[:, ~live] * _SIGN).max(axis=0)  # a row with no free column: its value is 0
        if dead_v.size and not float(dead_v.max()) <= CHECK_TOL:  # NaN fails too
            first = int(np.flatnonzero(~(dead_v <= CHECK_TOL))[0])  # segments in order, as _fixed_failure
            i = int(np.flatnonzero(~live)[first]) // nr.per_segment
            return LocalSolution(False, {}, f"horizontal norm bound of segment {segs[i]} exceeded by "
                                 f"{float(dead_v[first]):.3g} by jets held fixed", 0.0, n, 0)
        limn = limn[:, live]
        norm = (nr.G, limn)
        Gs = np.vstack([Gs, nr.G])
        tight = np.concatenate([tight, _tightened(limn, limn.shape[1], None)], axis=1)
    t0 = time.perf_counter()
    x, status = _solve_dense(st.P.copy(), q, Gs, tight[0], tight[1], backend)
    qp_time = time.perf_counter() - t0
    if x is None:
        fixed = _fixed_failure(jets, durations, bounds, corridor_of, segs, pos, n)
        return fixed or LocalSolution(False, {}, f"QP {status} for jets {free}", qp_time, n, nl)
    viol = max(float(((lim - G.dot(x)) * _SIGN).max()), 0.0)  # lo - Gx and Gx - hi, every row
    if norm is not None:
        viol = max(viol, float(((norm[1] - norm[0].dot(x)) * _SIGN).max()))
    if not viol <= CHECK_TOL:  # NaN fails too
        fixed = _fixed_failure(jets, durations, bounds, corridor_of, segs, pos, n)
        return fixed or LocalSolution(False, {}, f"QP solution misses a row by {viol:.3g} for jets {free}", qp_time, n, nl)
    out: dict[int, FloatArray] = {}
    for j, p in pos.items():
        jet = np.array(jets[j], dtype=float)
        jet[1:] = x[NV * p : NV * p + NV].reshape(JET_ORDER - 1, 3)
        out[j] = jet
    return LocalSolution(True, out, "ok", qp_time, n, nl)


def _fixed_failure(
    jets: Mapping[int, FloatArray],
    durations: Mapping[int, float],
    bounds: Bounds,
    corridor_of: CorridorOf,
    segs: Sequence[int],
    pos: Mapping[int, int],
    n: int,
) -> LocalSolution | None:
    """The first row (segments in order, bounds before corridor) that fixed jets already violate, named."""
    lim = hodograph_limits(bounds)
    for s in segs:
        mt = segment_mats(float(durations[s]), s in pos, s + 1 in pos)
        lay = mt.layout
        base = mt.arrays["qfix"] @ np.concatenate([jets[s], jets[s + 1]])
        v = base[HODO_ROWS].ravel()[lay.dead_b]
        over = np.maximum(v - lim[1].ravel()[lay.dead_b], lim[0].ravel()[lay.dead_b] - v)
        if over.size and not float(over.max()) <= CHECK_TOL:
            i = int(np.argmax(over)) if not np.isnan(over).any() else int(np.flatnonzero(np.isnan(over))[0])
            k = int(ORDER_OF_ROW[int(lay.dead_b[i]) // 3])
            return LocalSolution(False, {}, f"{ORDER_NAMES[k]} bound of segment {s} violated by "
                                 f"{float(over[i]):.3g} by jets held fixed", 0.0, n, 0)
        poly = corridor_of(s)
        if poly is not None and poly.A.shape[0] and lay.dead_c.size:
            worst = float((base[lay.dead_c] @ poly.A.T - poly.b).max())
            if not worst <= CHECK_TOL:
                return LocalSolution(False, {}, f"corridor of segment {s} violated by "
                                     f"{worst:.3g} by jets held fixed", 0.0, n, 0)
    return None
