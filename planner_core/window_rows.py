"""The compiled pass's rows, never stored: each is built from its segment's hull map, column
scales and corridor faces when it joins the working set (`materialize`), and a segment's rows
are checked by evaluating its control and hodograph points once (`seg_check`). `fill_rows`
stacks rows for the numpy + daqp path and the global QP. Compiled by numba; imported through
`window_kernel`, which keeps numba's cache of the whole pass fresh (`kernel_jit.refresh_cache`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from planner_core.kernel_jit import NV, njit, njit_inline


@njit_inline
def row_dot(ab: Any, r: int, ja: int, jb: int, x: Any) -> float:
    """g_r' x over the window's columns: `ja`/`jb` = local index of the segment's start/end jet or -1.

    Four partial sums (one chain of dependent adds is latency bound) and unsigned indices (no
    wraparound test per load; views cost more to build than these 24 products): ~16 ns a row."""
    s0 = 0.0
    s1 = 0.0
    s2 = 0.0
    s3 = 0.0
    ru = np.uint64(r)
    for side in range(2):
        j = ja if side == 0 else jb
        if j >= 0:
            o = np.uint64(NV * j)
            c = np.uint64(NV * side)
            for k in range(0, NV, 4):
                ku = np.uint64(k)
                s0 += ab[ru, c + ku] * x[o + ku]
                s1 += ab[ru, c + ku + np.uint64(1)] * x[o + ku + np.uint64(1)]
                s2 += ab[ru, c + ku + np.uint64(2)] * x[o + ku + np.uint64(2)]
                s3 += ab[ru, c + ku + np.uint64(3)] * x[o + ku + np.uint64(3)]
    return (s0 + s1) + (s2 + s3)


@njit_inline
def seg_rows(s: int, f0: int, f1: int, half: bool, off: Any, n1: Any, n2: Any) -> tuple[int, int, int, int]:
    """Rows [ra, rb) of segment s in the window f0..f1, local index of its start/end jet (-1: fixed)."""
    if s == f0 - 1:
        return off[s] + n1[s], off[s + 1], -1, 0
    if s < f1:
        return off[s], off[s + 1], s - f0, s + 1 - f0
    if half:
        return off[s], off[s] + n1[s], f1 - f0, -1
    return off[s], off[s] + n1[s] + n2[s], f1 - f0, -1


@njit_inline
def row_loc(lr: int, bn1: int, nb: int, f: int) -> tuple[int, int, int]:
    """Local row `lr` of a segment with f faces -> (kind, index, point): kind 0 a bound row
    (index: its place among the bound rows), 1 / 2 a corridor row on P(1+point) / P(5+point)
    (index: the face). Layout, as `window._RowStore` stacks them: [start-only bounds | corridor
    on P1..P4 | both | end-only bounds | corridor on P5..P8]."""
    if lr < bn1:
        return 0, lr, 0
    q = lr - bn1
    if q < 4 * f:
        return 1, q % f, q // f
    t = lr - 4 * f
    if t < nb:
        return 0, t, 0
    q = t - nb
    return 2, q % f, q // f


@njit_inline
def seg_points(s: int, ua: Any, ub: Any, hull: Any, w: Any, f: int, nz: Any, need_a: bool, need_b: bool,
                pts: Any) -> None:
    """Control points P1..P8 (when the segment has faces) and hodograph points of segment s,
    per axis, from its jets' derivatives (unscaled, (4, 3)): `ua` at the start, `ub` at the end.

    Points that involve the start jet only (no nonzero in the end jet's run of `nz[k]`) are
    computed when `need_a`, the others when `need_b`: the first and the last segment of a window
    need one kind each."""
    nh = hull.shape[1]  # 10 control points, then the certified hodograph points
    jm = pts[nh : nh + 10]  # the 10 x 3 [p0; start derivatives; p1; end derivatives]
    for d in range(3):
        jm[0, d] = w[s, d]
        jm[5, d] = w[s + 1, d]
        for c in range(4):
            jm[1 + c, d] = ua[c, d]
            jm[6 + c, d] = ub[c, d]
    k0 = 1 if f > 0 else 10
    for k in range(k0, nh):
        if not (need_b if nz[k, 3] > nz[k, 2] else need_a):
            continue
        for d in range(3):
            v = 0.0
            for c in range(10):  # a fixed trip count unrolls; the nonzero runs alone measured slower
                v += hull[s, k, c] * jm[c, d]
            pts[k, d] = v


@njit_inline
def seg_check(
    s: int, lra: int, lrb: int, ua: Any, ub: Any, klo: int, khi: int, tol: float, hull: Any, pr: Any,
    pd: Any, bn1: int, nb: int, face_off: Any, pa: Any, w: Any, b6: Any, f6: Any, nz: Any, pts: Any, bad: Any,
) -> int:
    """Rows [lra, lrb) of segment s outside limits klo / khi (see `_lim`) by more than `tol`, given
    its jets' derivatives: their local indices into `bad`, and their count. Each row reads a
    hodograph point or dots a control point with a face; loops by region, so no row needs a
    division to find its face."""
    fo = face_off[s]
    f = face_off[s + 1] - fo
    n1 = bn1 + 4 * f  # rows [0, n1) involve the start jet only
    seg_points(s, ua, ub, hull, w, f, nz, lra < n1, lrb > n1, pts)
    nbad = 0
    # a horizontal norm's polygon rows (axis 3) come in runs of one point's directions, with one
    # limit: a point inside the circle of that radius satisfies all of them (|n . c| <= |c|)
    last = -1
    inside = False
    x = y = 0.0
    for lr in range(max(lra, 0), min(lrb, bn1)):
        d = pd[lr]
        if d < 3:
            v = pts[10 + pr[lr], d]
        else:  # a horizontal polygon direction, in b6[6:8]
            if pr[lr] != last:
                last = pr[lr]
                x, y = pts[10 + last, 0], pts[10 + last, 1]
                lim = min(b6[khi, lr], -b6[klo, lr]) + tol
                inside = lim > 0.0 and x * x + y * y <= lim * lim
            if inside:
                continue
            v = b6[6, lr] * x + b6[7, lr] * y
        if v > b6[khi, lr] + tol or v < b6[klo, lr] - tol:
            bad[nbad] = lr
            nbad += 1
    c0, c1 = bn1 + 4 * f, nb + 4 * f
    for lr in range(max(lra, c0), min(lrb, c1)):
        t = lr - 4 * f
        d = pd[t]
        if d < 3:
            v = pts[10 + pr[t], d]
        else:
            if pr[t] != last:
                last = pr[t]
                x, y = pts[10 + last, 0], pts[10 + last, 1]
                lim = min(b6[khi, t], -b6[klo, t]) + tol
                inside = lim > 0.0 and x * x + y * y <= lim * lim
            if inside:
                continue
            v = b6[6, t] * x + b6[7, t] * y
        if v > b6[khi, t] + tol or v < b6[klo, t] - tol:
            bad[nbad] = lr
            nbad += 1
    for side in range(2):
        base = bn1 if side == 0 else c1
        if lrb <= base or lra >= base + 4 * f:
            continue
        for i in range(4):
            k = 1 + i if side == 0 else 5 + i
            for fi in range(f):
                lr = base + i * f + fi
                if lr < lra or lr >= lrb:
                    continue
                face = fo + fi
                v = pa[face, 0] * pts[k, 0] + pa[face, 1] * pts[k, 1] + pa[face, 2] * pts[k, 2]
                if v > f6[khi, face] + tol or v < f6[klo, face] - tol:
                    bad[nbad] = lr
                    nbad += 1
    return nbad


@njit_inline
def jet_derivs(jets: Any, j: int, out: Any) -> None:
    for c in range(4):
        for d in range(3):
            out[c, d] = jets[j, 1 + c, d]


@njit_inline
def x_derivs(x: Any, i: int, cs: Any, s: int, out: Any) -> None:
    """Unscaled derivatives of the window's local jet i (waypoint s) from its scaled unknowns."""
    for c in range(4):
        for d in range(3):
            out[c, d] = x[NV * i + 3 * c + d] * cs[s, 3 * c + d]


@njit
def materialize(
    ids: Any, n: int, r0: int, rseg: Any, rowa: Any, rowb: Any, off: Any, hull: Any, cs: Any, pr: Any,
    pd: Any, bn1: int, nb: int, face_off: Any, pa: Any, w: Any, b6: Any, f6: Any, xf: Any, wab: Any,
    nrm: Any, lim4: Any,
) -> None:
    """Window rows ids[:n] join the working set: coefficients into wab[i] (24: start jet | end
    jet, columns scaled by `cs`), norm over the free columns, limits less the constant part
    (waypoints and fixed jets) into lim4[:, i] (lo_t, hi_t, lo_w, hi_w; `b6` per bound row and
    `f6` per face hold lo_t, hi_t, lo, hi, lo_w, hi_w).

    Rows are built when a window needs them (its working set) instead of stored: a row comes
    from its segment's hull map (10 + n, 10), the column scales and its faces. Stored densely they
    were ~60 MB at m = 1000, and filling them cost more than half the pass.

    One call for many rows, the row code written out here: a call with this many array
    arguments, even inlined, costs ~0.1 us (reference counting) against ~10 ns for the row."""
    for ii in range(n):
        i = ids[ii]
        s = rseg[i]
        fo = face_off[s]
        kind, idx, pt = row_loc(r0 + i - off[s], bn1, nb, face_off[s + 1] - fo)
        for k in range(2 * NV):
            wab[i, k] = 0.0
        if kind == 0 and pd[idx] < 3:
            d = pd[idx]
            r = 10 + pr[idx]
            for c in range(4):
                wab[i, 3 * c + d] = hull[s, r, 1 + c] * cs[s, 3 * c + d]
                wab[i, NV + 3 * c + d] = hull[s, r, 6 + c] * cs[s + 1, 3 * c + d]
            g = hull[s, r, 0] * w[s, d] + hull[s, r, 5] * w[s + 1, d]
        elif kind == 0:  # a horizontal polygon direction (b6[6:8]) on a certified point
            r = 10 + pr[idx]
            for e in range(2):
                de = b6[6 + e, idx]
                for c in range(4):
                    wab[i, 3 * c + e] = hull[s, r, 1 + c] * de * cs[s, 3 * c + e]
                    wab[i, NV + 3 * c + e] = hull[s, r, 6 + c] * de * cs[s + 1, 3 * c + e]
            g = hull[s, r, 0] * (b6[6, idx] * w[s, 0] + b6[7, idx] * w[s, 1]) + hull[s, r, 5] * (
                b6[6, idx] * w[s + 1, 0] + b6[7, idx] * w[s + 1, 1])
        elif kind == 1:
            face = fo + idx
            r = 1 + pt
            for c in range(4):
                hc = hull[s, r, 1 + c]
                for e in range(3):
                    wab[i, 3 * c + e] = hc * pa[face, e] * cs[s, 3 * c + e]
            g = hull[s, r, 0] * (pa[face, 0] * w[s, 0] + pa[face, 1] * w[s, 1] + pa[face, 2] * w[s, 2])
        else:
            face = fo + idx
            r = 5 + pt
            for c in range(4):
                hc = hull[s, r, 6 + c]
                for e in range(3):
                    wab[i, NV + 3 * c + e] = hc * pa[face, e] * cs[s + 1, 3 * c + e]
            g = hull[s, r, 5] * (pa[face, 0] * w[s + 1, 0] + pa[face, 1] * w[s + 1, 1] + pa[face, 2] * w[s + 1, 2])
        nn = 0.0
        if rowa[i] < 0:
            for k in range(NV):
                g += wab[i, k] * xf[k]
        else:
            for k in range(NV):
                nn += wab[i, k] * wab[i, k]
        if rowb[i] < 0:
            for k in range(NV):
                g += wab[i, NV + k] * xf[NV + k]
        else:
            for k in range(NV):
                nn += wab[i, NV + k] * wab[i, NV + k]
        nrm[i] = np.sqrt(nn)
        if kind == 0:
            for k in range(4):
                lim4[k, i] = b6[k if k < 2 else k + 2, idx] - g
        else:
            for k in range(4):
                lim4[k, i] = f6[k if k < 2 else k + 2, fo + idx] - g


@njit
def nonzero_runs(hull: Any) -> Any:
    """(10 + n, 4): per hull row, the bounds of its nonzero run among columns 0..4 and among 5..9
    (the pattern is structural: the same for every segment; d > 0 only scales entries)."""
    nh = hull.shape[1]
    nz = np.zeros((nh, 4), dtype=np.int64)
    if hull.shape[0] == 0:
        return nz
    for k in range(nh):
        for side in range(2):
            lo, hi = 5 * side + 5, 5 * side
            for c in range(5 * side, 5 * side + 5):
                if hull[0, k, c] != 0.0:
                    lo = min(lo, c)
                    hi = c + 1
            if hi <= lo:
                lo, hi = 5 * side, 5 * side
            for c in range(lo, hi):
                if hull[0, k, c] == 0.0:
                    hi = -1  # not one run: take the whole side
            if hi < 0:
                lo, hi = 5 * side, 5 * side + 5
            nz[k, 2 * side] = lo
            nz[k, 2 * side + 1] = hi
    return nz


@njit
def fill_rows(
    segs: Any, off: Any, hull: Any, w: Any, cs: Any, pr: Any, pd: Any, bdir: Any, bn1: int, blim: Any,
    face_off: Any, pa: Any, pb: Any, inf: float, margin: float,
    ab: Any, c0: Any, lim: Any, limw: Any, add_tol: float,
) -> None:
    """Stacked rows of the given segments, in the layout of `window._RowStore` (see there):
    [start-only bounds | corridor P1..P4 | both | end-only bounds | corridor P5..P8]; columns
    scaled by `cs`. Writes `ab`, `c0`, limits `lim` (lo_t, hi_t, lo, hi) and working limits `limw`
    (tightened, and tightened widened by `add_tol` relative; skipped when it has no columns).
    The numpy + daqp window path and the global QP read these; the compiled pass builds the
    rows it needs itself (`materialize`)."""
    nb = pr.size
    extras = limw.shape[1] > 0
    for si in range(segs.size):
        s = segs[si]
        f = face_off[s + 1] - face_off[s]
        base = off[s]
        n = off[s + 1] - base
        # this segment's rows as views: loops from 0 drop numba's negative-index tests
        blk = ab[base : base + n]
        blk[:, :] = 0.0
        cz = c0[base : base + n]
        hs = hull[s]
        csa = cs[s]
        csb = cs[s + 1]
        wa = w[s]
        wb = w[s + 1]
        for t in range(nb):
            d = pd[t]
            row = blk[t + (4 * f if t >= bn1 else 0)]
            hr = hs[10 + pr[t]]
            if d < 3:
                for c in range(4):
                    row[3 * c + d] = hr[1 + c] * csa[3 * c + d]
                    row[NV + 3 * c + d] = hr[6 + c] * csb[3 * c + d]
                cz[t + (4 * f if t >= bn1 else 0)] = hr[0] * wa[d] + hr[5] * wb[d]
            else:  # a horizontal polygon direction bdir[t] (z component 0)
                for e in range(2):
                    de = bdir[t, e]
                    for c in range(4):
                        row[3 * c + e] = hr[1 + c] * de * csa[3 * c + e]
                        row[NV + 3 * c + e] = hr[6 + c] * de * csb[3 * c + e]
                cz[t + (4 * f if t >= bn1 else 0)] = hr[0] * (bdir[t, 0] * wa[0] + bdir[t, 1] * wa[1]) + hr[5] * (
                    bdir[t, 0] * wb[0] + bdir[t, 1] * wb[1])
        for k in range(4):
            lk = lim[k, base : base + n]
            bk = blim[k]
            for t in range(nb):
                lk[t + (4 * f if t >= bn1 else 0)] = bk[t]
        for i in range(4):
            for fi in range(f):
                face = face_off[s] + fi
                hi = min(max(pb[face], -inf), inf)
                hi_t = hi - margin * (1.0 + abs(hi)) if hi < inf else hi
                pf = pa[face]
                for side in range(2):
                    if side == 0:
                        r = bn1 + i * f + fi
                        hr = hs[1 + i]
                        qc, col, wp, cw = 1, 0, wa, csa
                    else:
                        r = nb + 4 * f + i * f + fi
                        hr = hs[5 + i]
                        qc, col, wp, cw = 6, NV, wb, csb
                    row = blk[r]
                    for c in range(4):
                        hc = hr[qc + c]
                        for e in range(3):
                            row[col + 3 * c + e] = hc * pf[e] * cw[3 * c + e]
                    cz[r] = hr[qc - 1] * (pf[0] * wp[0] + pf[1] * wp[1] + pf[2] * wp[2])
                    lim[0, base + r] = -inf
                    lim[1, base + r] = hi_t
                    lim[2, base + r] = -inf
                    lim[3, base + r] = hi
        if not extras:
            continue
        l0, l1 = lim[0, base : base + n], lim[1, base : base + n]
        w0, w1 = limw[0, base : base + n], limw[1, base : base + n]
        w2, w3 = limw[2, base : base + n], limw[3, base : base + n]
        for r in range(n):
            lo_t = l0[r]
            hi_t = l1[r]
            w0[r] = lo_t
            w1[r] = hi_t
            w2[r] = lo_t - add_tol * (1.0 + abs(lo_t))
            w3[r] = hi_t + add_tol * (1.0 + abs(hi_t))

