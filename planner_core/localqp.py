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
(read-only arrays), so a call is a few batched numpy products and one daqp solve.
"""

from __future__ import annotations

import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from functools import lru_cache
from math import prod

import numpy as np
from numpy.typing import NDArray

from planner_core.certificate import (
    HODO_ROWS,
    INNER_POINTS,
    LIMIT_INDEX,
    N_HODO,
    ORDER_OF_ROW,
    POWER_EXPONENTS,
    POWER_LO,
    hodograph_limits,
    power_table,
    read_only,
)
from planner_core.constraints import (
    KIND_BOUND,
    cost_matrices,
    hull_maps,
    segment_rows,
    unit_cost,
    unit_templates,
)
from planner_core.problem import (
    DEGREE,
    JET_ORDER,
    N_CTRL,
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
_NV = 12  # velocity..snap x 3 axes per free jet
_INF = 1e30  # both QP backends' "no bound"
_SIGN = np.array([[1.0], [-1.0]])  # row 0 lower limits, row 1 upper limits


@dataclass(frozen=True)
class _Layout:
    """What a segment's QP block looks like for one choice of free sides, at every duration.

    `unit` holds every duration-scaled array of `_SegmentMats` at d = 1, flattened end to
    end; `power` is the index of each entry's power of d in `power_table`.
    """

    unit: FloatArray
    power: NDArray[np.int64]
    parts: tuple[tuple[str, int, int, tuple[int, ...]], ...]
    live_b: NDArray[np.int64]  # flat (point * 3 + axis) hodograph values that depend on a free entry
    dead_b: NDArray[np.int64]
    live_c: NDArray[np.int64]  # control-point rows (of the hull rows) that depend on a free entry
    dead_c: NDArray[np.int64]


def _expand(blk: FloatArray, other: FloatArray) -> FloatArray:
    """Rows (i, f) x columns (order, axis): blk[i, order] * other[f, axis]."""
    r, c = blk.shape
    f, a = other.shape
    return np.asarray((blk[:, None, :, None] * other[None, :, None, :]).reshape(r * f, c * a))


def _expand_power(p: NDArray[np.int64]) -> NDArray[np.int64]:
    """The power of each entry of `_expand(blk, eye(3))` given blk's powers."""
    return np.asarray(np.repeat(np.repeat(p, 3, axis=0), 3, axis=1), dtype=np.int64)


@lru_cache(maxsize=4)
def _free_layout(free0: bool, free1: bool) -> _Layout:
    q1, hpow, _, _ = unit_templates()
    k1, kpow_f = unit_cost(4)
    kpow = kpow_f.astype(np.int64)
    cols = {side: np.arange(side * JET_ORDER + 1, side * JET_ORDER + JET_ORDER) for side, f in ((0, free0), (1, free1)) if f}
    fixed = np.ones(2 * JET_ORDER, dtype=bool)
    for c in cols.values():
        fixed[c] = False
    qb, qi = q1[HODO_ROWS], q1[INNER_POINTS]
    live_b = np.zeros(qb.shape[0], dtype=bool)
    live_c = np.zeros(qi.shape[0], dtype=bool)
    for c in cols.values():
        live_b |= np.any(qb[:, c] != 0.0, axis=1)
        live_c |= np.any(qi[:, c] != 0.0, axis=1)
    eye3 = np.eye(3)
    entries: list[tuple[str, FloatArray, NDArray[np.int64]]] = [("qfix", q1 * fixed, hpow)]
    for sa, ca in cols.items():
        entries.append((f"gb{sa}", _expand(qb[live_b][:, ca], eye3), _expand_power(hpow[HODO_ROWS][live_b][:, ca])))
        entries.append((f"qc{sa}", qi[live_c][:, ca], hpow[INNER_POINTS][live_c][:, ca]))
        entries.append((f"kq{sa}", 2.0 * k1[ca] * fixed, kpow[ca]))
        for sb, cb in cols.items():
            ix = np.ix_(ca, cb)
            entries.append((f"p{sa}{sb}", 2.0 * _expand(k1[ix], eye3), _expand_power(kpow[ix])))
    parts = []
    start = 0
    for name, arr, _ in entries:
        parts.append((name, start, start + arr.size, arr.shape))
        start += arr.size
    axes = np.arange(3)
    return _Layout(
        unit=read_only(np.concatenate([a.ravel() for _, a, _ in entries])),
        power=np.concatenate([p.ravel() for _, _, p in entries]) - POWER_LO,
        parts=tuple(parts),
        live_b=(np.flatnonzero(live_b)[:, None] * 3 + axes).ravel(),
        dead_b=(np.flatnonzero(~live_b)[:, None] * 3 + axes).ravel(),
        live_c=np.flatnonzero(live_c) + 1,
        dead_c=np.flatnonzero(~live_c) + 1,
    )


@dataclass(frozen=True)
class _SegmentMats:
    """One segment's QP block at one duration, for one choice of free sides.

    arrays: "qfix" (10 + n, 10) hull map with the free entries' columns zeroed; per free side a,
    "gb<a>" (3 * live points, 12) bound rows, "qc<a>" (live points, 4) corridor coefficients
    per axis, "kq<a>" (4, 10) cost gradient rows (fixed entries only); per pair of free
    sides, "p<a><b>" (12, 12) cost Hessian blocks.
    """

    layout: _Layout
    arrays: dict[str, FloatArray]


@lru_cache(maxsize=512)  # ~10 kB each: a few MB at most on the companion
def _segment_mats(d: float, free0: bool, free1: bool) -> _SegmentMats:
    lay = _free_layout(free0, free1)
    flat = read_only(lay.unit * power_table(d).take(lay.power))
    return _SegmentMats(lay, {name: flat[a:b].reshape(shape) for name, a, b, shape in lay.parts})


@dataclass(frozen=True)
class _Pattern:
    """The shape of one local QP: which rows exist and where, for one choice of free jets and
    corridor face counts, at any durations.

    Row order: live bound rows, live corridor rows (segment, control point, face) --
    the QP's rows, `n_live` of them -- then rows that depend on fixed entries only:
    dead bound rows, dead corridor rows. Those are zero in G, never handed to the
    solver, and checked with the solution in one pass.
    """

    n: int
    jets: tuple[int, ...]  # offsets (from the first segment) of the jets the QP reads, in order
    col_of: dict[int, int]  # jet offset -> its position in `jets`
    n_bound: int
    n_live: int
    n_rows: int
    n_dead_bound: int
    live_b: NDArray[np.int64]  # hodograph values (of the 3 n k) with a bound row in the QP
    dead_b: NDArray[np.int64]
    face_off: tuple[int, ...]  # per segment, offset of its (9, faces) corridor values in the flat vector
    live_c: NDArray[np.int64]  # flat indices into the corridor values of the rows handed to the solver
    dead_c: NDArray[np.int64]
    corridor_blocks: tuple[tuple[int, int, int, int], ...]  # (segment, first row, column, free side)
    uniform_col: int | None  # one free side per segment, all in these columns, one face count
    # `_structure`'s numbers as one scatter-add: entry e of the segments' unit layouts, scaled by
    # the power `power[e]` of its segment's duration table, adds into `dest[e]` of a flat buffer
    unit: FloatArray
    power: NDArray[np.int64]  # into the (k, 12) table of the segments' durations' powers, flattened
    dest: NDArray[np.int64]  # buf_size (one past the end) for entries the QP does not use
    buf_size: int
    regions: dict[str, tuple[int, tuple[int, ...]]]  # name -> (offset, shape) in the buffer (_scatter_plan)


@lru_cache(maxsize=256)
def _pattern(n_free: int, pat: tuple[tuple[int, int, int, int], ...]) -> _Pattern:
    """pat: per segment (offset from the first, position of its start jet among the free ones
    or -1, same for its end jet, corridor faces)."""
    k = len(pat)
    jet_offs = sorted({o + e for o, *_ in pat for e in (0, 1)})
    lives, deads, lcs, dcs = [], [], [], []
    blocks: list[tuple[int, int, int, int]] = []  # (segment, rows, column, side)
    face_off = []
    fo = 0
    for i, (_, p0, p1, faces) in enumerate(pat):
        lay = _free_layout(p0 >= 0, p1 >= 0)
        lives.append(i * 3 * N_HODO + lay.live_b)
        deads.append(i * 3 * N_HODO + lay.dead_b)
        face_off.append(fo)
        if faces:
            f = np.arange(faces)
            lcs.append((fo + lay.live_c[:, None] * faces + f).ravel())
            dcs.append((fo + lay.dead_c[:, None] * faces + f).ravel())
            blocks.extend((i, lay.live_c.size * faces, _NV * p, side) for side, p in ((0, p0), (1, p1)) if p >= 0)
        fo += DEGREE * faces
    live_b = np.concatenate(lives)
    placed = []  # corridor blocks' first rows: after the bound rows, segment after segment
    r = live_b.size
    last_seg = -1
    for i, nrows, col, side in blocks:
        if i != last_seg:
            start, last_seg = r, i
            r += nrows
        placed.append((i, start, col, side))
    empty = np.zeros(0, dtype=np.int64)
    dead_b = np.concatenate(deads)
    dead_c = np.concatenate(dcs) if dcs else empty
    one_each = [i for i, *_ in placed] == list(range(k))
    cols = {col for _, _, col, _ in placed}
    same_points = len({_free_layout(p0 >= 0, p1 >= 0).live_c.size for _, p0, p1, _ in pat}) == 1
    uniform = one_each and len(cols) == 1 and same_points and len({fc for *_, fc in pat}) == 1
    n = _NV * n_free
    col_of = {o: i for i, o in enumerate(jet_offs)}
    unit, power, dest, size, regions = _scatter_plan(n_free, pat, col_of, r + dead_b.size + dead_c.size, placed)
    return _Pattern(
        n=n,
        jets=tuple(jet_offs),
        col_of=col_of,
        n_bound=live_b.size,
        n_live=r,
        n_rows=r + dead_b.size + dead_c.size,
        n_dead_bound=dead_b.size,
        live_b=live_b,
        dead_b=dead_b,
        face_off=tuple(face_off),
        live_c=np.concatenate(lcs) if lcs else empty,
        dead_c=dead_c,
        corridor_blocks=tuple(placed),
        uniform_col=cols.pop() if uniform else None,
        unit=unit,
        power=power,
        dest=dest,
        buf_size=size,
        regions=regions,
    )


_Regions = dict[str, tuple[int, tuple[int, ...]]]


def _block_index(region: tuple[int, tuple[int, ...]], row0: int, col0: int, rows: int, cols: int) -> NDArray[np.int64]:
    """Flat buffer indices of the (rows, cols) block at (row0, col0) of a 2-d region."""
    off, shape = region
    return np.asarray(off + (row0 + np.arange(rows))[:, None] * shape[-1] + col0 + np.arange(cols), dtype=np.int64)


def _place(
    dest: NDArray[np.int64], part: tuple[int, tuple[int, ...]], region: tuple[int, tuple[int, ...]], row0: int, col0: int
) -> None:
    """Send a layout part (its offset in the unit vector, its 2-d shape) to a block of a region."""
    start, (rows, cols) = part
    dest[start : start + rows * cols] = _block_index(region, row0, col0, rows, cols).ravel()


def _scatter_plan(
    n_free: int,
    pat: tuple[tuple[int, int, int, int], ...],
    col_of: dict[int, int],
    n_rows: int,
    blocks: list[tuple[int, int, int, int]],
) -> tuple[FloatArray, NDArray[np.int64], NDArray[np.int64], int, _Regions]:
    """Where each entry of each segment's `_SegmentMats` layout goes in `_structure`'s buffer.

    Regions: "hodo" (n k, 5 nj), "inner" (9 k, 5 nj), "grad" (4 n_free, 5 nj), "P" (n, n),
    "G" (rows, n), then "qc<i>.<side>" per corridor block, one after the other ("qc": all
    of them). Sums (P, grad) come out of the scatter-add; unused entries go one past the end.
    """
    k, n, nj = len(pat), _NV * n_free, len(col_of)
    shapes: list[tuple[str, tuple[int, ...]]] = [
        ("hodo", (k * N_HODO, JET_ORDER * nj)),
        ("inner", (k * DEGREE, JET_ORDER * nj)),
        ("grad", ((JET_ORDER - 1) * n_free, JET_ORDER * nj)),
        ("P", (n, n)),
        ("G", (n_rows, n)),
    ]
    layouts = [_free_layout(p0 >= 0, p1 >= 0) for _, p0, p1, _ in pat]
    parts = [{name: (a, shape) for name, a, _, shape in lay.parts} for lay in layouts]
    shapes += [(f"qc{i}.{side}", parts[i][f"qc{side}"][1]) for i, _, _, side in blocks]
    regions: _Regions = {}
    size = 0
    for name, shape in shapes:
        regions[name] = (size, shape)
        size += prod(shape)
    qc0 = regions["G"][0] + prod(regions["G"][1])
    regions["qc"] = (qc0, (size - qc0,))

    units, powers, dests = [], [], []
    r = 0
    for i, ((o, p0, p1, _), lay, part) in enumerate(zip(pat, layouts, parts, strict=True)):
        dest = np.full(lay.unit.size, size, dtype=np.int64)
        c = JET_ORDER * col_of[o]  # the segment's two jets are adjacent in `jets`
        qfix = np.full((N_CTRL + N_HODO, 2 * JET_ORDER), size, dtype=np.int64)
        qfix[:DEGREE] = _block_index(regions["inner"], DEGREE * i, c, DEGREE, 2 * JET_ORDER)
        qfix[HODO_ROWS] = _block_index(regions["hodo"], N_HODO * i, c, N_HODO, 2 * JET_ORDER)
        start = part["qfix"][0]
        dest[start : start + qfix.size] = qfix.ravel()
        sides = [(side, p) for side, p in ((0, p0), (1, p1)) if p >= 0]
        nbi = 0
        for sa, pa in sides:
            _place(dest, part[f"kq{sa}"], regions["grad"], (JET_ORDER - 1) * pa, c)
            _place(dest, part[f"gb{sa}"], regions["G"], r, _NV * pa)
            nbi = part[f"gb{sa}"][1][0]
            for sb, pb in sides:
                _place(dest, part[f"p{sa}{sb}"], regions["P"], _NV * pa, _NV * pb)
            if f"qc{i}.{sa}" in regions:
                _place(dest, part[f"qc{sa}"], regions[f"qc{i}.{sa}"], 0, 0)
        r += nbi
        units.append(lay.unit)
        powers.append(i * POWER_EXPONENTS.size + lay.power)
        dests.append(dest)
    return read_only(np.concatenate(units)), np.concatenate(powers), np.concatenate(dests), size, regions


@dataclass(frozen=True)
class _Structure:
    """The numbers of one local QP that depend only on its pattern and the durations.

    Per call there remain the fixed jets' contribution (a few products with the
    matrices here), the corridor rows' numbers (polytope-dependent) and the solve.
    """

    pat: _Pattern
    hodo: FloatArray  # (n k, 5 nj): fixed entries of the jets -> every segment's hodograph points
    inner: FloatArray  # (9 k, 5 nj): same -> control points P^0..P^8
    grad: FloatArray  # (4 n_free, 5 nj): same -> cost gradient, per axis
    P: FloatArray  # (n, n)
    G: FloatArray  # (rows, n): live bound rows filled, corridor rows zero, dead rows zero
    qc: tuple[FloatArray, ...]  # per corridor block, (points, 4) coefficients per axis
    uniform_qc: FloatArray | None  # (k, points, 4) when the pattern is uniform


@lru_cache(maxsize=128)  # ~40 kB each for one free jet
def _structure(n_free: int, pat: tuple[tuple[int, int, int, int], ...], ds: tuple[float, ...]) -> _Structure:
    """ds: the segments' durations, in the order of `pat`. One scatter-add builds every number."""
    pt = _pattern(n_free, pat)
    table = np.power(np.array(ds)[:, None], POWER_EXPONENTS).ravel()
    # float64: bincount with float weights sums them (P and grad entries shared by two segments)
    sums = np.bincount(pt.dest, weights=pt.unit * table.take(pt.power), minlength=pt.buf_size + 1)
    buf = read_only(np.asarray(sums, dtype=np.float64))

    def view(name: str) -> FloatArray:
        off, shape = pt.regions[name]
        return buf[off : off + prod(shape)].reshape(shape)

    qc = tuple(view(f"qc{i}.{side}") for i, _, _, side in pt.corridor_blocks)
    uniform_qc = None
    if pt.uniform_col is not None:  # one block per segment, stored one after the other
        off = pt.regions["qc"][0]
        uniform_qc = buf[off : off + sum(q.size for q in qc)].reshape(len(qc), *qc[0].shape)
    return _Structure(
        pat=pt,
        hodo=view("hodo"),
        inner=view("inner"),
        grad=view("grad"),
        P=view("P"),
        G=view("G"),
        qc=qc,
        uniform_qc=uniform_qc,
    )


@lru_cache(maxsize=64)
def _bound_limits(bounds_key: bytes, k: int) -> tuple[FloatArray, bool]:
    """(2, 3 n k) lower / upper bound of every certified hodograph value of k segments; all finite?"""
    lim = np.tile(np.frombuffer(bounds_key, dtype=np.float64)[LIMIT_INDEX], (1, k))
    return read_only(lim), bool(np.isfinite(lim).all())


def _bounds_key(bounds: Bounds) -> bytes:
    return np.concatenate((bounds.lo, bounds.hi), axis=None).tobytes()


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
    durations, face counts and bounds comes from caches (`_structure`,
    `_bound_limits`); per call, a few products give the fixed jets' part, then
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
    st = _structure(len(free), pat_key, ds_key)
    pt = st.pat
    n, k, nb, nl = pt.n, len(segs), pt.n_bound, pt.n_live
    limits, finite = _bound_limits(_bounds_key(bounds), k)
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
        G[nb:nl, col : col + _NV] = expanded.reshape(-1, _NV)
    else:
        vc = np.empty(pt.face_off[-1] + DEGREE * faces[-1])
        for i, poly in enumerate(polys):
            if faces[i] and poly is not None:
                o = pt.face_off[i]
                vc[o : o + DEGREE * faces[i]] = (vi[DEGREE * i : DEGREE * (i + 1)].dot(poly.A.T) - poly.b).ravel()
        for (i, r0, col, _), qc in zip(pt.corridor_blocks, st.qc, strict=True):
            poly = polys[i]
            assert poly is not None  # blocks exist only for segments with faces
            G[r0 : r0 + qc.shape[0] * faces[i], col : col + _NV] = _expand(qc, poly.A)
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
        nr = _norm_structure(len(free), pat_key, ds_key, tuple(bool(v) for v in np.isfinite(bounds.horizontal)),
                             bounds.sides)
        limn = _norm_limits(nr, bounds, values)
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
        jet[1:] = x[_NV * p : _NV * p + _NV].reshape(JET_ORDER - 1, 3)
        out[j] = jet
    return LocalSolution(True, out, "ok", qp_time, n, nl)


@dataclass(frozen=True)
class _NormRows:
    """The horizontal norm's polygon rows of one local QP pattern at its durations (cached: they
    depend on nothing else); per call only their constants and limits are computed."""

    G: FloatArray  # (live rows, n): rows that depend on a free entry
    live: NDArray[np.bool_]  # (R,)
    base: NDArray[np.int64]  # (k p,) index of each normed point's x value among the certified values
    normals: FloatArray  # (d, 2)
    order: NDArray[np.int64]  # (R,) derivative order of each row
    per_segment: int


@lru_cache(maxsize=256)
def _norm_structure(n_free: int, pat: tuple[tuple[int, int, int, int], ...], ds: tuple[float, ...],
                    orders: tuple[bool, ...], sides: int) -> _NormRows:
    """A row is normal . (x, y) of one certified point: the same combination of that point's x
    and y bound rows (the structure's live bound rows; a dead value's row is zero)."""
    from planner_core.constraints import polygon_normals

    st = _structure(n_free, pat, ds)
    pt = st.pat
    k, n = len(pat), pt.n
    normed = np.array([orders[o - 1] for o in ORDER_OF_ROW])
    pts = np.flatnonzero(normed)
    normals = polygon_normals(sides)
    full = np.zeros((k * 3 * N_HODO, n))
    full[pt.live_b] = st.G[: pt.n_bound]
    base = ((np.arange(k)[:, None] * N_HODO + pts[None, :]).ravel() * 3).astype(np.int64)
    gx, gy = full[base], full[base + 1]  # (k p, n)
    rows = (normals[None, :, 0, None] * gx[:, None, :] + normals[None, :, 1, None] * gy[:, None, :]).reshape(-1, n)
    live = np.any(rows != 0.0, axis=1)
    order = np.repeat(np.tile(ORDER_OF_ROW[pts], k), normals.shape[0]).astype(np.int64)
    for a in (live, base, order):
        a.setflags(write=False)
    return _NormRows(read_only(np.ascontiguousarray(rows[live])), live, base, normals, order,
                     int(pts.size * normals.shape[0]))


def _norm_limits(nr: _NormRows, bounds: Bounds, values: FloatArray) -> FloatArray:
    """(2, R) the polygon rows' limits less their fixed part (`values`: every certified value of
    the QP's segments, from the fixed entries)."""
    cx, cy = values[nr.base], values[nr.base + 1]
    const = (nr.normals[None, :, 0] * cx[:, None] + nr.normals[None, :, 1] * cy[:, None]).ravel()
    r = bounds.polygon_radius[nr.order - 1]
    return np.stack([-r - const, r - const])


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
        mt = _segment_mats(float(durations[s]), s in pos, s + 1 in pos)
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
