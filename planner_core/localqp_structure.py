"""The cached structure of `localqp.solve_derivatives` (a local replan's QP): everything that
depends only on the free-jet pattern, the face counts, the durations or the bounds, built once
and kept read-only.

- per segment: `free_layout` (its QP block at d = 1 for one choice of free sides) and
  `segment_mats` (that block at one duration);
- per QP: `qp_pattern` (which rows exist and where) and `qp_structure` (its numbers at given
  durations, one scatter-add), `bound_limits` (the hodograph limits), `norm_structure` /
  `norm_limits` (the horizontal norm's polygon rows).
"""

from __future__ import annotations

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
    power_table,
    read_only,
)
from planner_core.constraints import unit_cost, unit_templates
from planner_core.problem import DEGREE, JET_ORDER, N_CTRL, Bounds, FloatArray

NV = 12  # velocity..snap x 3 axes per free jet


@dataclass(frozen=True)
class SegmentLayout:
    """What a segment's QP block looks like for one choice of free sides, at every duration.

    `unit` holds every duration-scaled array of `SegmentMats` at d = 1, flattened end to
    end; `power` is the index of each entry's power of d in `power_table`.
    """

    unit: FloatArray
    power: NDArray[np.int64]
    parts: tuple[tuple[str, int, int, tuple[int, ...]], ...]
    live_b: NDArray[np.int64]  # flat (point * 3 + axis) hodograph values that depend on a free entry
    dead_b: NDArray[np.int64]
    live_c: NDArray[np.int64]  # control-point rows (of the hull rows) that depend on a free entry
    dead_c: NDArray[np.int64]


def expand(blk: FloatArray, other: FloatArray) -> FloatArray:
    """Rows (i, f) x columns (order, axis): blk[i, order] * other[f, axis]."""
    r, c = blk.shape
    f, a = other.shape
    return np.asarray((blk[:, None, :, None] * other[None, :, None, :]).reshape(r * f, c * a))


def expand_power(p: NDArray[np.int64]) -> NDArray[np.int64]:
    """The power of each entry of `expand(blk, eye(3))` given blk's powers."""
    return np.asarray(np.repeat(np.repeat(p, 3, axis=0), 3, axis=1), dtype=np.int64)


@lru_cache(maxsize=4)
def free_layout(free0: bool, free1: bool) -> SegmentLayout:
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
        entries.append((f"gb{sa}", expand(qb[live_b][:, ca], eye3), expand_power(hpow[HODO_ROWS][live_b][:, ca])))
        entries.append((f"qc{sa}", qi[live_c][:, ca], hpow[INNER_POINTS][live_c][:, ca]))
        entries.append((f"kq{sa}", 2.0 * k1[ca] * fixed, kpow[ca]))
        for sb, cb in cols.items():
            ix = np.ix_(ca, cb)
            entries.append((f"p{sa}{sb}", 2.0 * expand(k1[ix], eye3), expand_power(kpow[ix])))
    parts = []
    start = 0
    for name, arr, _ in entries:
        parts.append((name, start, start + arr.size, arr.shape))
        start += arr.size
    axes = np.arange(3)
    return SegmentLayout(
        unit=read_only(np.concatenate([a.ravel() for _, a, _ in entries])),
        power=np.concatenate([p.ravel() for _, _, p in entries]) - POWER_LO,
        parts=tuple(parts),
        live_b=(np.flatnonzero(live_b)[:, None] * 3 + axes).ravel(),
        dead_b=(np.flatnonzero(~live_b)[:, None] * 3 + axes).ravel(),
        live_c=np.flatnonzero(live_c) + 1,
        dead_c=np.flatnonzero(~live_c) + 1,
    )


@dataclass(frozen=True)
class SegmentMats:
    """One segment's QP block at one duration, for one choice of free sides.

    arrays: "qfix" (10 + n, 10) hull map with the free entries' columns zeroed; per free side a,
    "gb<a>" (3 * live points, 12) bound rows, "qc<a>" (live points, 4) corridor coefficients
    per axis, "kq<a>" (4, 10) cost gradient rows (fixed entries only); per pair of free
    sides, "p<a><b>" (12, 12) cost Hessian blocks.
    """

    layout: SegmentLayout
    arrays: dict[str, FloatArray]


@lru_cache(maxsize=512)  # ~10 kB each: a few MB at most on the companion
def segment_mats(d: float, free0: bool, free1: bool) -> SegmentMats:
    lay = free_layout(free0, free1)
    flat = read_only(lay.unit * power_table(d).take(lay.power))
    return SegmentMats(lay, {name: flat[a:b].reshape(shape) for name, a, b, shape in lay.parts})


@dataclass(frozen=True)
class QpPattern:
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
    # `qp_structure`'s numbers as one scatter-add: entry e of the segments' unit layouts, scaled by
    # the power `power[e]` of its segment's duration table, adds into `dest[e]` of a flat buffer
    unit: FloatArray
    power: NDArray[np.int64]  # into the (k, 12) table of the segments' durations' powers, flattened
    dest: NDArray[np.int64]  # buf_size (one past the end) for entries the QP does not use
    buf_size: int
    regions: dict[str, tuple[int, tuple[int, ...]]]  # name -> (offset, shape) in the buffer (_scatter_plan)


@lru_cache(maxsize=256)
def qp_pattern(n_free: int, pat: tuple[tuple[int, int, int, int], ...]) -> QpPattern:
    """pat: per segment (offset from the first, position of its start jet among the free ones
    or -1, same for its end jet, corridor faces)."""
    k = len(pat)
    jet_offs = sorted({o + e for o, *_ in pat for e in (0, 1)})
    lives, deads, lcs, dcs = [], [], [], []
    blocks: list[tuple[int, int, int, int]] = []  # (segment, rows, column, side)
    face_off = []
    fo = 0
    for i, (_, p0, p1, faces) in enumerate(pat):
        lay = free_layout(p0 >= 0, p1 >= 0)
        lives.append(i * 3 * N_HODO + lay.live_b)
        deads.append(i * 3 * N_HODO + lay.dead_b)
        face_off.append(fo)
        if faces:
            f = np.arange(faces)
            lcs.append((fo + lay.live_c[:, None] * faces + f).ravel())
            dcs.append((fo + lay.dead_c[:, None] * faces + f).ravel())
            blocks.extend((i, lay.live_c.size * faces, NV * p, side) for side, p in ((0, p0), (1, p1)) if p >= 0)
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
    same_points = len({free_layout(p0 >= 0, p1 >= 0).live_c.size for _, p0, p1, _ in pat}) == 1
    uniform = one_each and len(cols) == 1 and same_points and len({fc for *_, fc in pat}) == 1
    n = NV * n_free
    col_of = {o: i for i, o in enumerate(jet_offs)}
    unit, power, dest, size, regions = _scatter_plan(n_free, pat, col_of, r + dead_b.size + dead_c.size, placed)
    return QpPattern(
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
    """Where each entry of each segment's `SegmentMats` layout goes in `qp_structure`'s buffer.

    Regions: "hodo" (n k, 5 nj), "inner" (9 k, 5 nj), "grad" (4 n_free, 5 nj), "P" (n, n),
    "G" (rows, n), then "qc<i>.<side>" per corridor block, one after the other ("qc": all
    of them). Sums (P, grad) come out of the scatter-add; unused entries go one past the end.
    """
    k, n, nj = len(pat), NV * n_free, len(col_of)
    shapes: list[tuple[str, tuple[int, ...]]] = [
        ("hodo", (k * N_HODO, JET_ORDER * nj)),
        ("inner", (k * DEGREE, JET_ORDER * nj)),
        ("grad", ((JET_ORDER - 1) * n_free, JET_ORDER * nj)),
        ("P", (n, n)),
        ("G", (n_rows, n)),
    ]
    layouts = [free_layout(p0 >= 0, p1 >= 0) for _, p0, p1, _ in pat]
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
            _place(dest, part[f"gb{sa}"], regions["G"], r, NV * pa)
            nbi = part[f"gb{sa}"][1][0]
            for sb, pb in sides:
                _place(dest, part[f"p{sa}{sb}"], regions["P"], NV * pa, NV * pb)
            if f"qc{i}.{sa}" in regions:
                _place(dest, part[f"qc{sa}"], regions[f"qc{i}.{sa}"], 0, 0)
        r += nbi
        units.append(lay.unit)
        powers.append(i * POWER_EXPONENTS.size + lay.power)
        dests.append(dest)
    return read_only(np.concatenate(units)), np.concatenate(powers), np.concatenate(dests), size, regions


@dataclass(frozen=True)
class QpStructure:
    """The numbers of one local QP that depend only on its pattern and the durations.

    Per call there remain the fixed jets' contribution (a few products with the
    matrices here), the corridor rows' numbers (polytope-dependent) and the solve.
    """

    pat: QpPattern
    hodo: FloatArray  # (n k, 5 nj): fixed entries of the jets -> every segment's hodograph points
    inner: FloatArray  # (9 k, 5 nj): same -> control points P^0..P^8
    grad: FloatArray  # (4 n_free, 5 nj): same -> cost gradient, per axis
    P: FloatArray  # (n, n)
    G: FloatArray  # (rows, n): live bound rows filled, corridor rows zero, dead rows zero
    qc: tuple[FloatArray, ...]  # per corridor block, (points, 4) coefficients per axis
    uniform_qc: FloatArray | None  # (k, points, 4) when the pattern is uniform


@lru_cache(maxsize=128)  # ~40 kB each for one free jet
def qp_structure(n_free: int, pat: tuple[tuple[int, int, int, int], ...], ds: tuple[float, ...]) -> QpStructure:
    """ds: the segments' durations, in the order of `pat`. One scatter-add builds every number."""
    pt = qp_pattern(n_free, pat)
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
    return QpStructure(
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
def bound_limits(bounds_key: bytes, k: int) -> tuple[FloatArray, bool]:
    """(2, 3 n k) lower / upper bound of every certified hodograph value of k segments; all finite?"""
    lim = np.tile(np.frombuffer(bounds_key, dtype=np.float64)[LIMIT_INDEX], (1, k))
    return read_only(lim), bool(np.isfinite(lim).all())


def bounds_key(bounds: Bounds) -> bytes:
    return np.concatenate((bounds.lo, bounds.hi), axis=None).tobytes()


@dataclass(frozen=True)
class NormRows:
    """The horizontal norm's polygon rows of one local QP pattern at its durations (cached: they
    depend on nothing else); per call only their constants and limits are computed."""

    G: FloatArray  # (live rows, n): rows that depend on a free entry
    live: NDArray[np.bool_]  # (R,)
    base: NDArray[np.int64]  # (k p,) index of each normed point's x value among the certified values
    normals: FloatArray  # (d, 2)
    order: NDArray[np.int64]  # (R,) derivative order of each row
    per_segment: int


@lru_cache(maxsize=256)
def norm_structure(n_free: int, pat: tuple[tuple[int, int, int, int], ...], ds: tuple[float, ...],
                    orders: tuple[bool, ...], sides: int) -> NormRows:
    """A row is normal . (x, y) of one certified point: the same combination of that point's x
    and y bound rows (the structure's live bound rows; a dead value's row is zero)."""
    from planner_core.constraints import polygon_normals

    st = qp_structure(n_free, pat, ds)
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
    return NormRows(read_only(np.ascontiguousarray(rows[live])), live, base, normals, order,
                     int(pts.size * normals.shape[0]))


def norm_limits(nr: NormRows, bounds: Bounds, values: FloatArray) -> FloatArray:
    """(2, R) the polygon rows' limits less their fixed part (`values`: every certified value of
    the QP's segments, from the fixed entries)."""
    cx, cy = values[nr.base], values[nr.base + 1]
    const = (nr.normals[None, :, 0] * cx[:, None] + nr.normals[None, :, 1] * cy[:, None]).ravel()
    r = bounds.polygon_radius[nr.order - 1]
    return np.stack([-r - const, r - const])
