"""Compiled receding-window pass: the iterative planner's hot loop without Python in it.

Same QP per waypoint as `window.WindowSolver.solve` (same rows, same tightened
limits, same cost blocks); what differs is the solver and where rows live:

- the Hessian of a window is block tridiagonal in its jets (segment s couples
  jets s and s+1 only), so it is factored block by block (per axis: 4 x 4
  blocks, the Hessian being the same on each axis);
- the QP is solved by the dual active-set method of Goldfarb and Idnani in its
  range-space form: every step needs one block-tridiagonal solve H^-1 n and
  a Cholesky factor of the small matrix S = N H^-1 N' of the active normals,
  grown by one row per added constraint. Rows are sparse (24 of the window's
  columns), so a slack costs 24 flops;
- rows are not stored: a row joining the working set is built from its
  segment's hull map, column scales and faces (`_materialize`), and the check of
  every row of the window evaluates each segment's control and hodograph points
  once and reads the rows off them (`_seg_check`). Stored densely, the rows
  were ~60 MB at m = 1000 and filling them took longer than the solves;
- only a working set of rows is searched for violations (rows active at the
  previous window and the open end's rows, as in `WindowSolver`), then every
  row of the window is checked against its tightened limit; violated rows join
  and the dual method simply goes on from where it stopped (its iterate stays
  dual feasible when rows are added).

A step that fails in any way (factorisation, infeasible, iteration cap, a row
outside its limit after the solve) stops the pass at that waypoint; the caller
settles it with the general path (which also recovers and diagnoses) and
resumes. Nothing is committed that failed the check against the tightened
rows, which implies the untightened ones.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any, TypeVar, cast

import numpy as np
from numba import njit as _njit
from numba import types as _types

F = TypeVar("F", bound=Callable[..., Any])
NV = 12
MAX_ADDS = 400  # constraint additions per window before giving up (typical: ~10)
MAX_ROUNDS = 8  # working-set growth rounds per window


def _jit(fn: F, **kw: Any) -> F:
    # numpy's error model: no zero-division branch in every inner loop (divisors are checked)
    try:
        return cast(F, _njit(cache=True, error_model="numpy", **kw)(fn))
    except RuntimeError:  # no writable cache location (read-only install, no NUMBA_CACHE_DIR)
        return cast(F, _njit(cache=False, error_model="numpy", **kw)(fn))


def njit(fn: F) -> F:
    """numba's decorator, typed, cached on disk so that each process does not compile again
    (compiling everything here takes ~20 s; loading it from the cache ~0.3 s)."""
    return _jit(fn)


def njit_inline(fn: F) -> F:
    """`njit`, inlined into its callers at the numba IR level (tiny helpers in the inner loops)."""
    return _jit(fn, inline="always")


def cache_state() -> str:
    """`warm` when numba's on-disk cache holds the compiled pass of this source (loading it:
    ~0.4 s), `cold` when the first call compiles it (~20 s here; a new install or an edit of
    this file), `unknown` when numba's cache cannot be read."""
    try:
        cache = cast(Any, run_pass)._cache  # numba internals, hence the guard
        if type(cache).__name__ == "NullCache":  # no writable cache: every process compiles
            return "cold"
        return "warm" if cache._cache_file._load_index() else "cold"
    except Exception:  # any change of numba's internals: say so, do not fail a plan
        return "unknown"


@njit
def _chol(a: Any) -> bool:
    """In-place lower Cholesky of a small block (upper part left as is)."""
    n = a.shape[0]
    for j in range(n):
        rj = a[j]
        d = rj[j]
        for k in range(j):
            d -= rj[k] * rj[k]
        if not d > 0.0:
            return False
        d = np.sqrt(d)
        rj[j] = d
        for i in range(n - j - 1):
            ri = a[j + 1 + i]
            s = ri[j]
            for k in range(j):
                s -= ri[k] * rj[k]
            ri[j] = s / d
    return True


@njit
def _btd_factor(ld: Any, lo: Any, nf: int) -> bool:
    """Block-tridiagonal Cholesky: `ld[i]` holds diagonal block i (in: H's, out: L's, lower),
    `lo[i]` (i >= 1) holds H[i-1, i] on entry and L[i, i-1] on exit.

    The window's Hessian is the same on every axis (the cost is a sum over axes, the column
    scales do not depend on the axis), H = H4 (x) I3 in the jets' (order, axis) layout: so
    this factors the per-axis H4 with 4 x 4 blocks (27x fewer flops than 12 x 12 blocks)."""
    nb = ld.shape[1]
    if not _chol(ld[0]):
        return False
    x = np.empty((nb, nb))
    for i in range(1, nf):
        e = lo[i]  # H[i-1, i]; L[i, i-1] = (L[i-1]^-1 H[i-1, i])'
        p = ld[i - 1]
        for r in range(nb):
            xr = x[r]
            er = e[r]
            for c in range(nb):
                xr[c] = er[c]
            pr = p[r]
            for k in range(r):
                pk = pr[k]
                xk = x[k]
                for c in range(nb):
                    xr[c] -= pk * xk[c]
            inv = 1.0 / pr[r]
            for c in range(nb):
                xr[c] *= inv
        for r in range(nb):
            er = e[r]
            for c in range(nb):
                er[c] = x[c, r]
        d = ld[i]
        for r in range(nb):
            dr = d[r]
            er = e[r]
            for c in range(r + 1):
                ec = e[c]
                s = 0.0
                for k in range(nb):
                    s += er[k] * ec[k]
                dr[c] -= s
        if not _chol(d):
            return False
    return True


@njit
def _btd_solve(ld: Any, lo: Any, nf: int, b: Any, y: Any) -> None:
    """y = H^-1 b with the per-axis factor of `_btd_factor` (H = H4 (x) I3): one
    block-tridiagonal solve per axis on the entries (jet i, order c, axis d) = 12 i + 3 c + d.

    Here and below, loops index views from 0 where they can: numba proves such indices
    non-negative and drops its negative-index test, which otherwise blocks vectorisation."""
    nb = ld.shape[1]
    t = np.empty(nb * nf)
    for d in range(3):
        for i in range(nf):
            for c in range(nb):
                t[nb * i + c] = b[NV * i + 3 * c + d]
        for i in range(nf):
            tc = t[nb * i : nb * i + nb]
            li = ld[i]
            for r in range(nb):
                s = tc[r]
                if i > 0:
                    tp = t[nb * i - nb : nb * i]
                    lr = lo[i, r]
                    for k in range(nb):
                        s -= lr[k] * tp[k]
                lrow = li[r]
                for k in range(r):
                    s -= lrow[k] * tc[k]
                tc[r] = s / lrow[r]
        for i in range(nf - 1, -1, -1):
            tc = t[nb * i : nb * i + nb]
            li = ld[i]
            if i < nf - 1:
                tn = t[nb * i + nb : nb * i + 2 * nb]
                ln = lo[i + 1]
                for k in range(nb):
                    c = tn[k]
                    lk = ln[k]
                    for r in range(nb):
                        tc[r] -= lk[r] * c
            for r in range(nb - 1, -1, -1):
                tc[r] /= li[r, r]
                c = tc[r]
                lrow = li[r]
                for k in range(r):
                    tc[k] -= lrow[k] * c
        for i in range(nf):
            for c in range(nb):
                y[NV * i + 3 * c + d] = t[nb * i + c]


@njit_inline
def _row_dot(ab: Any, r: int, ja: int, jb: int, x: Any) -> float:
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
def _seg_rows(s: int, f0: int, f1: int, half: bool, off: Any, n1: Any, n2: Any) -> tuple[int, int, int, int]:
    """Rows [ra, rb) of segment s in the window f0..f1, local index of its start/end jet (-1: fixed)."""
    if s == f0 - 1:
        return off[s] + n1[s], off[s + 1], -1, 0
    if s < f1:
        return off[s], off[s + 1], s - f0, s + 1 - f0
    if half:
        return off[s], off[s] + n1[s], f1 - f0, -1
    return off[s], off[s] + n1[s] + n2[s], f1 - f0, -1


@njit
def _chol_append(ls: Any, k: int, srow: Any) -> bool:
    """Grow the Cholesky factor `ls` of S (k x k) by the row `srow` (k + 1 entries)."""
    for j in range(k):
        s = srow[j]
        for i in range(j):
            s -= ls[k, i] * ls[j, i]
        ls[k, j] = s / ls[j, j]
    d = srow[k]
    for i in range(k):
        d -= ls[k, i] * ls[k, i]
    if not d > 1e-300:
        return False
    ls[k, k] = np.sqrt(d)
    return True


@njit
def _chol_solve(ls: Any, k: int, w: Any, out: Any) -> None:
    for i in range(k):
        s = w[i]
        for j in range(i):
            s -= ls[i, j] * out[j]
        out[i] = s / ls[i, i]
    for i in range(k - 1, -1, -1):
        s = out[i]
        for j in range(i + 1, k):
            s -= ls[j, i] * out[j]
        out[i] = s / ls[i, i]



CLOCK_MONOTONIC = 1  # Linux's id; time.perf_counter reads the same clock
# libc's clock_gettime, for `run_pass` to time its steps (~50 ns a call): an external symbol that
# numba's JIT resolves in the process and the ahead-of-time build (`build_kernel`) leaves to the
# dynamic linker, so both builds compile this same source. objmode around time.perf_counter took
# ~20 us a step, more than the step.
_clock_gettime: Any = _types.ExternalFunction("clock_gettime", _types.int32(_types.int32, _types.voidptr))


@njit_inline
def _now(ts: Any) -> float:
    _clock_gettime(CLOCK_MONOTONIC, ts.ctypes)
    t: float = ts[0] + 1e-9 * ts[1]
    return t


@njit_inline
def _row_loc(lr: int, bn1: int, nb: int, f: int) -> tuple[int, int, int]:
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
def _seg_points(s: int, ua: Any, ub: Any, hull: Any, w: Any, f: int, nz: Any, need_a: bool, need_b: bool,
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
def _seg_check(
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
    _seg_points(s, ua, ub, hull, w, f, nz, lra < n1, lrb > n1, pts)
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
def _jet_derivs(jets: Any, j: int, out: Any) -> None:
    for c in range(4):
        for d in range(3):
            out[c, d] = jets[j, 1 + c, d]


@njit_inline
def _x_derivs(x: Any, i: int, cs: Any, s: int, out: Any) -> None:
    """Unscaled derivatives of the window's local jet i (waypoint s) from its scaled unknowns."""
    for c in range(4):
        for d in range(3):
            out[c, d] = x[NV * i + 3 * c + d] * cs[s, 3 * c + d]


@njit
def _materialize(
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
        kind, idx, pt = _row_loc(r0 + i - off[s], bn1, nb, face_off[s + 1] - fo)
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
def _step(
    f0: int, f1: int, half: bool, m: int,
    off: Any, n1: Any, n2: Any, hull: Any, cs: Any, pr: Any, pd: Any, bn1: int, nb: int, face_off: Any,
    pa: Any, w: Any, b6: Any, f6: Any,
    k8: Any, kdd: Any, qpos: Any, qsum: Any, kba4: Any, kab4: Any, jets: Any, active: Any, ws: Any,
    check_tol: float,
) -> bool:
    """Solve window f0..f1 into `ws` (its x: scaled derivatives); False on any doubt."""
    (ld, lo, q, x, v, z, nvec, vmat, ls, w_, rr, lam, act_r, act_sd, rowa, rowb, rseg,
     lim4, cand, srow, clist, bad, xf, wab, nrm, pts, ua, ub, nz) = ws
    lo_t, hi_t, lo_w, hi_w = lim4[0], lim4[1], lim4[2], lim4[3]
    nf = f1 - f0 + 1
    nx = NV * nf
    sb = f0 - 1
    r0 = off[sb] + n1[sb]
    r1 = off[f1] + n1[f1] + (0 if half else n2[f1])
    nr = r1 - r0
    # constants: rows that depend only on a fixed jet must hold as they are
    if f0 == 1:
        _jet_derivs(jets, 0, ua)
        ub[:, :] = 0.0
        if _seg_check(0, 0, n1[0], ua, ub, 2, 3, check_tol, hull, pr, pd, bn1, nb, face_off, pa, w, b6, f6,
                      nz, pts, bad):
            return False
    if not half:
        ua[:, :] = 0.0
        _jet_derivs(jets, f1 + 1, ub)
        if _seg_check(f1, n1[f1] + n2[f1], off[f1 + 1] - off[f1], ua, ub, 2, 3, check_tol, hull, pr, pd, bn1,
                      nb, face_off, pa, w, b6, f6, nz, pts, bad):
            return False
    for k in range(NV):
        xf[k] = jets[sb, 1 + k // 3, k % 3] / cs[sb, k]
        xf[NV + k] = 0.0 if half else jets[f1 + 1, 1 + k // 3, k % 3] / cs[f1 + 1, k]
    for s in range(sb, f1 + 1):
        ra, rb, ja, jb = _seg_rows(s, f0, f1, half, off, n1, n2)
        for i in range(ra - r0, rb - r0):
            rowa[i] = ja
            rowb[i] = jb
            rseg[i] = s
    # working set: rows active at the previous window, and the open end's rows (the last jet is
    # pushed against them: the cost does not see that segment)
    hb = off[f1] - r0 if half else nr
    nc = 0
    for i in range(nr):
        cand[i] = active[r0 + i] or i >= hb
        if cand[i]:
            clist[nc] = i
            nc += 1
    _materialize(clist, nc, r0, rseg, rowa, rowb, off, hull, cs, pr, pd, bn1, nb, face_off, pa, w, b6, f6, xf,
                 wab, nrm, lim4)
    # cost: block-tridiagonal Hessian (per axis, 4 x 4 blocks) and gradient; per-waypoint sums
    # precomputed
    for i in range(nf):
        wp = f0 + i
        last_half = half and i == nf - 1
        for a in range(NV):
            q[NV * i + a] = qpos[wp - 1, NV + a] if last_half else qsum[wp, a]
        for a in range(4):
            for b in range(4):
                ld[i, a, b] = k8[wp - 1, 4 + a, 4 + b] if last_half else kdd[wp, a, b]
                if i > 0:
                    lo[i, a, b] = k8[wp - 1, a, 4 + b]
    # gradient from the fixed neighbours' derivatives, per axis (4 x 4 blocks, the same on each)
    for a in range(4):
        for d in range(3):
            g = 0.0
            for c in range(4):
                g += kba4[sb, a, c] * jets[sb, 1 + c, d]
            q[3 * a + d] += g
    if not half:
        o = nx - NV
        for a in range(4):
            for d in range(3):
                g = 0.0
                for c in range(4):
                    g += kab4[f1, a, c] * jets[f1 + 1, 1 + c, d]
                q[o + 3 * a + d] += g
    if not _btd_factor(ld, lo, nf):
        return False
    # Goldfarb-Idnani from the unconstrained minimum
    for i in range(nx):
        nvec[i] = -q[i]
    _btd_solve(ld, lo, nf, nvec, x)
    for i in range(nx):
        nvec[i] = 0.0
    k = 0
    adds = 0
    rounds = 0
    while True:
        # most violated working row (violation per unit normal)
        best = 0.0
        p = -1
        ps = 0
        for ci in range(nc):
            i = clist[ci]
            gx = _row_dot(wab, i, rowa[i], rowb[i], x)
            vl = lo_t[i] - gx
            vh = gx - hi_t[i]
            # a quarter of the final check's margin: what passes here passes there
            tl = 0.25 * (lo_t[i] - lo_w[i])
            th = 0.25 * (hi_w[i] - hi_t[i])
            if vl > tl or vh > th:
                nn = nrm[i]
                if nn < 1e-300:
                    return False  # a violated row with no free column: the constants broke it
                sc = (vl if vl > tl else vh) / nn
                if sc > best:
                    best = sc
                    p = i
                    ps = 1 if vl > tl else -1
        if p < 0:
            # working set satisfied: check every row of the window, grow the set if needed
            grew = False
            for s in range(sb, f1 + 1):
                ra, rb, ja, jb = _seg_rows(s, f0, f1, half, off, n1, n2)
                if ja >= 0:
                    _x_derivs(x, ja, cs, s, ua)
                else:
                    _jet_derivs(jets, s, ua)
                if jb >= 0:
                    _x_derivs(x, jb, cs, s + 1, ub)
                elif half:
                    ub[:, :] = 0.0  # the open end: its rows here do not involve it
                else:
                    _jet_derivs(jets, s + 1, ub)
                os_ = off[s]
                nbad = _seg_check(s, ra - os_, rb - os_, ua, ub, 4, 5, 0.0, hull, pr, pd, bn1, nb, face_off, pa, w,
                                  b6, f6, nz, pts, bad)
                n0 = nc
                for b in range(nbad):
                    i = os_ + bad[b] - r0
                    if cand[i]:
                        return False  # missed by more than rounding: let the general path decide
                    cand[i] = True
                    clist[nc] = i
                    nc += 1
                    grew = True
                if nc > n0:
                    _materialize(clist[n0:], nc - n0, r0, rseg, rowa, rowb, off, hull, cs, pr, pd, bn1, nb, face_off,
                                 pa, w, b6, f6, xf, wab, nrm, lim4)
            if not grew:
                break
            rounds += 1
            if rounds > MAX_ROUNDS:
                return False
            continue
        adds += 1
        if adds > MAX_ADDS:
            return False
        # normal n_p = sign * g_p (dense), v = H^-1 n_p
        ja, jb = rowa[p], rowb[p]
        if ja >= 0:
            for kk in range(NV):
                nvec[NV * ja + kk] = ps * wab[p, kk]
        if jb >= 0:
            for kk in range(NV):
                nvec[NV * jb + kk] = ps * wab[p, NV + kk]
        _btd_solve(ld, lo, nf, nvec, v)
        bp = lo_t[p] if ps > 0 else -hi_t[p]
        lam_p = 0.0
        while True:
            # z = v - V' S^-1 N v (primal step direction), r = S^-1 N v (dual)
            for j in range(k):
                w_[j] = act_sd[j] * _row_dot(wab, act_r[j], rowa[act_r[j]], rowb[act_r[j]], v)
            _chol_solve(ls, k, w_, rr)
            for i in range(nx):
                acc = v[i]
                for j in range(k):
                    acc -= vmat[j, i] * rr[j]
                z[i] = acc
            zn = ps * _row_dot(wab, p, ja, jb, z)
            nv_ = ps * _row_dot(wab, p, ja, jb, v)
            t1 = np.inf
            drop = -1
            for j in range(k):
                if rr[j] > 0.0:
                    t = lam[j] / rr[j]
                    if t < t1:
                        t1 = t
                        drop = j
            sp = ps * _row_dot(wab, p, ja, jb, x) - bp
            t2 = np.inf
            if zn > 1e-13 * nv_:
                t2 = max(-sp, 0.0) / zn
            t = min(t1, t2)
            if t == np.inf:
                return False  # infeasible: the general path diagnoses it
            if t2 < np.inf:
                for i in range(nx):
                    x[i] += t * z[i]
            for j in range(k):
                lam[j] -= t * rr[j]
            lam_p += t
            if t2 <= t1:
                # full step: p joins the active set. At most nx independent rows fit (the
                # workspace holds nx + 1): more means rows dependent up to rounding that the
                # factor let through; writing past it corrupted memory (a 10-piece straight leg)
                if k >= nx:
                    return False  # let the general path decide
                for j in range(k):
                    srow[j] = ps * _row_dot(wab, p, ja, jb, vmat[j])
                srow[k] = nv_
                if not _chol_append(ls, k, srow):
                    return False
                for i in range(nx):
                    vmat[k, i] = v[i]
                act_r[k] = p
                act_sd[k] = ps
                lam[k] = lam_p
                k += 1
                break
            # partial step: drop the blocking constraint, refactor S
            for j in range(drop, k - 1):
                act_r[j] = act_r[j + 1]
                act_sd[j] = act_sd[j + 1]
                lam[j] = lam[j + 1]
                for i in range(nx):
                    vmat[j, i] = vmat[j + 1, i]
            k -= 1
            for a in range(k):
                ia = act_r[a]
                for b in range(a + 1):
                    srow[b] = act_sd[a] * _row_dot(wab, ia, rowa[ia], rowb[ia], vmat[b])
                if not _chol_append(ls, a, srow):
                    return False
        for i in range(nx):
            nvec[i] = 0.0
    # commit: active flags for the next window, derivatives scaled back
    actw = active[r0:r1]
    for i in range(nr):
        actw[i] = False
    for j in range(k):
        if lam[j] > 0.0:
            active[r0 + act_r[j]] = True
    return True


@njit
def _nonzero_runs(hull: Any) -> Any:
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
def run_pass(
    j0: int, window: int, m: int,
    off: Any, n1: Any, n2: Any, hull: Any, cs: Any, pr: Any, pd: Any, bn1: int, nb: int, face_off: Any,
    pa: Any, w: Any, b6: Any, f6: Any,
    k8: Any, kdd: Any, qpos: Any, qsum: Any, kba4: Any, kab4: Any, jets: Any, guess: Any, active: Any,
    step_times: Any, check_tol: float, ts: Any,
) -> int:
    """Steps j0 .. m-2; commits the jet at each j. Returns the first j it could not settle (m-1
    when it settled all). `step_times[j]`: seconds spent on step j.

    Rows: `hull` (S, 10 + n, 10) maps each segment's [p0, start derivatives, p1, end derivatives] to
    its control and hodograph points; `cs` the column scales; `pr`/`pd` the hodograph row and axis
    of each bound row (in `_RowStore`'s order, `bn1` of them start-only, `nb` in all; axis 3: a
    horizontal norm's polygon direction, (b6[6], b6[7]) its x, y components); corridor
    faces `pa` (segment s: rows face_off[s]:face_off[s+1]); limits per bound row `b6` (8, .) and per
    face `f6` (6, .): lo_t, hi_t, lo, hi, lo_w, hi_w (see `_lim`), b6 then the direction; `off`/`n1`/`n2` the stacked row
    offsets, for `active` (the rows active at the last solution). `ts`: two int64 for
    libc's clock_gettime (see `_now`)."""
    hmax = window
    nxm = NV * hmax
    rmax = 0
    for s in range(m - 1):
        cnt = off[s + 1] - off[s]
        if cnt > rmax:
            rmax = cnt
    nrm = rmax * (hmax + 2)
    ws = (
        np.zeros((hmax, 4, 4)), np.zeros((hmax, 4, 4)), np.zeros(nxm), np.zeros(nxm),
        np.zeros(nxm), np.zeros(nxm), np.zeros(nxm), np.zeros((nxm + 1, nxm)),
        np.zeros((nxm + 1, nxm + 1)), np.zeros(nxm + 1), np.zeros(nxm + 1),
        np.zeros(nxm + 1), np.zeros(nxm + 1, dtype=np.int64), np.zeros(nxm + 1, dtype=np.int64),
        np.zeros(nrm, dtype=np.int64), np.zeros(nrm, dtype=np.int64), np.zeros(nrm, dtype=np.int64),
        np.zeros((4, nrm)), np.zeros(nrm, dtype=np.bool_),
        np.zeros(nxm + 1), np.zeros(nrm, dtype=np.int64), np.zeros(rmax, dtype=np.int64), np.zeros(2 * NV),
        np.zeros((nrm, 2 * NV)), np.zeros(nrm), np.zeros((hull.shape[1] + 10, 3)), np.zeros((4, 3)), np.zeros((4, 3)),
        _nonzero_runs(hull),
    )
    x = ws[3]
    t0 = _now(ts)
    for j in range(j0, m - 1):
        f1 = min(j + window - 1, m - 2)
        half = f1 < m - 2
        ok = _step(j, f1, half, m, off, n1, n2, hull, cs, pr, pd, bn1, nb, face_off, pa, w, b6, f6,
                   k8, kdd, qpos, qsum, kba4, kab4, jets, active, ws, check_tol)
        if not ok:
            return j
        for i in range(f1 - j + 1):
            for k in range(NV):
                guess[j + i, 1 + k // 3, k % 3] = x[NV * i + k] * cs[j + i, k]
        for k in range(NV):
            jets[j, 1 + k // 3, k % 3] = guess[j, 1 + k // 3, k % 3]
        t1 = _now(ts)
        step_times[j] = t1 - t0
        t0 = t1
    return m - 1



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
    rows it needs itself (`_materialize`)."""
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
