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
  segment's hull map, column scales and faces (`materialize`), and the check of
  every row of the window evaluates each segment's control and hodograph points
  once and reads the rows off them (`seg_check`). Stored densely, the rows
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

from typing import Any, cast

import numpy as np
from numba import types as _types

from planner_core import kernel_aot
from planner_core.kernel_jit import COMPILED, NV, njit, njit_inline, refresh_cache
from planner_core.window_factor import btd_factor, btd_solve, chol_append, chol_solve
from planner_core.window_rows import (
    fill_rows,
    jet_derivs,
    materialize,
    nonzero_runs,
    row_dot,
    seg_check,
    seg_rows,
    x_derivs,
)

# The door to the compiled pass: importing the pass's parts through this module keeps numba's
# cache of all of them fresh (`CACHE`, below).
__all__ = ["CACHE", "MAX_ADDS", "MAX_ROUNDS", "cache_state", "fill_rows", "materialize", "nonzero_runs", "run_pass",
           "seg_check"]

MAX_ADDS = 400  # constraint additions per window before giving up (typical: ~10)
MAX_ROUNDS = 8  # working-set growth rounds per window


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
        jet_derivs(jets, 0, ua)
        ub[:, :] = 0.0
        if seg_check(0, 0, n1[0], ua, ub, 2, 3, check_tol, hull, pr, pd, bn1, nb, face_off, pa, w, b6, f6,
                      nz, pts, bad):
            return False
    if not half:
        ua[:, :] = 0.0
        jet_derivs(jets, f1 + 1, ub)
        if seg_check(f1, n1[f1] + n2[f1], off[f1 + 1] - off[f1], ua, ub, 2, 3, check_tol, hull, pr, pd, bn1,
                      nb, face_off, pa, w, b6, f6, nz, pts, bad):
            return False
    for k in range(NV):
        xf[k] = jets[sb, 1 + k // 3, k % 3] / cs[sb, k]
        xf[NV + k] = 0.0 if half else jets[f1 + 1, 1 + k // 3, k % 3] / cs[f1 + 1, k]
    for s in range(sb, f1 + 1):
        ra, rb, ja, jb = seg_rows(s, f0, f1, half, off, n1, n2)
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
    materialize(clist, nc, r0, rseg, rowa, rowb, off, hull, cs, pr, pd, bn1, nb, face_off, pa, w, b6, f6, xf,
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
    if not btd_factor(ld, lo, nf):
        return False
    # Goldfarb-Idnani from the unconstrained minimum
    for i in range(nx):
        nvec[i] = -q[i]
    btd_solve(ld, lo, nf, nvec, x)
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
            gx = row_dot(wab, i, rowa[i], rowb[i], x)
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
                ra, rb, ja, jb = seg_rows(s, f0, f1, half, off, n1, n2)
                if ja >= 0:
                    x_derivs(x, ja, cs, s, ua)
                else:
                    jet_derivs(jets, s, ua)
                if jb >= 0:
                    x_derivs(x, jb, cs, s + 1, ub)
                elif half:
                    ub[:, :] = 0.0  # the open end: its rows here do not involve it
                else:
                    jet_derivs(jets, s + 1, ub)
                os_ = off[s]
                nbad = seg_check(s, ra - os_, rb - os_, ua, ub, 4, 5, 0.0, hull, pr, pd, bn1, nb, face_off, pa, w,
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
                    materialize(clist[n0:], nc - n0, r0, rseg, rowa, rowb, off, hull, cs, pr, pd, bn1, nb, face_off,
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
        btd_solve(ld, lo, nf, nvec, v)
        bp = lo_t[p] if ps > 0 else -hi_t[p]
        lam_p = 0.0
        while True:
            # z = v - V' S^-1 N v (primal step direction), r = S^-1 N v (dual)
            for j in range(k):
                w_[j] = act_sd[j] * row_dot(wab, act_r[j], rowa[act_r[j]], rowb[act_r[j]], v)
            chol_solve(ls, k, w_, rr)
            for i in range(nx):
                acc = v[i]
                for j in range(k):
                    acc -= vmat[j, i] * rr[j]
                z[i] = acc
            zn = ps * row_dot(wab, p, ja, jb, z)
            nv_ = ps * row_dot(wab, p, ja, jb, v)
            t1 = np.inf
            drop = -1
            for j in range(k):
                if rr[j] > 0.0:
                    t = lam[j] / rr[j]
                    if t < t1:
                        t1 = t
                        drop = j
            sp = ps * row_dot(wab, p, ja, jb, x) - bp
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
                    srow[j] = ps * row_dot(wab, p, ja, jb, vmat[j])
                srow[k] = nv_
                if not chol_append(ls, k, srow):
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
                    srow[b] = act_sd[a] * row_dot(wab, ia, rowa[ia], rowb[ia], vmat[b])
                if not chol_append(ls, a, srow):
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
        nonzero_runs(hull),
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


# Before anything is loaded from numba's cache: a change of any kernel file compiles the pass again.
CACHE = refresh_cache(COMPILED, f"{kernel_aot.source_digest():016x}")
