"""The compiled pass's factorisations: the window's block-tridiagonal Hessian and the Cholesky
factor of the active normals' matrix S = N H^-1 N', grown one row at a time (see
`window_kernel`). Compiled by numba; imported through `window_kernel`, which keeps numba's
cache of the whole pass fresh (`kernel_jit.refresh_cache`).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from planner_core.kernel_jit import NV, njit


@njit
def chol(a: Any) -> bool:
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
def btd_factor(ld: Any, lo: Any, nf: int) -> bool:
    """Block-tridiagonal Cholesky: `ld[i]` holds diagonal block i (in: H's, out: L's, lower),
    `lo[i]` (i >= 1) holds H[i-1, i] on entry and L[i, i-1] on exit.

    The window's Hessian is the same on every axis (the cost is a sum over axes, the column
    scales do not depend on the axis), H = H4 (x) I3 in the jets' (order, axis) layout: so
    this factors the per-axis H4 with 4 x 4 blocks (27x fewer flops than 12 x 12 blocks)."""
    nb = ld.shape[1]
    if not chol(ld[0]):
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
        if not chol(d):
            return False
    return True


@njit
def btd_solve(ld: Any, lo: Any, nf: int, b: Any, y: Any) -> None:
    """y = H^-1 b with the per-axis factor of `btd_factor` (H = H4 (x) I3): one
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


@njit
def chol_append(ls: Any, k: int, srow: Any) -> bool:
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
def chol_solve(ls: Any, k: int, w: Any, out: Any) -> None:
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

