"""Exact primal-dual active-set refinement of an approximate QP solution (sparse KKT solves)."""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

from planner_core.problem import FloatArray
from planner_core.qp.result import INF, Matrix

if TYPE_CHECKING:
    import scipy.sparse as sp


def max_violation(G: Matrix, x: FloatArray, lo: FloatArray, hi: FloatArray) -> float:
    r = np.asarray(G @ x).ravel()
    if r.size == 0:
        return 0.0
    return float(max(np.max(r - hi), np.max(lo - r), 0.0))


def refine_active_set(
    P: Matrix,
    q: FloatArray,
    G: Matrix,
    lo: FloatArray,
    hi: FloatArray,
    x0: FloatArray,
    y0: FloatArray,
    *,
    tol: float = 1e-10,
    max_iter: int = 30,
) -> FloatArray | None:
    """Primal-dual active-set refinement from an approximate (x0, y0).

    Solves the equality-constrained KKT system on the guessed active set,
    then adds violated rows and drops rows whose multiplier has the wrong sign,
    until the active set is consistent. Returns None when it does not settle.
    """
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    Gs = sp.csr_matrix(G)
    Ps = sp.csc_matrix(P)
    n = Ps.shape[0]
    r0 = Gs @ x0
    scale = 1.0 + np.abs(np.where(np.abs(hi) < INF, hi, 0.0))
    upper = (y0 > 1e-9) | (r0 >= hi - 1e-7 * scale)
    lower = ((y0 < -1e-9) | (r0 <= lo + 1e-7 * scale)) & ~upper
    x = x0
    for _ in range(max_iter):
        act = np.flatnonzero(upper | lower)
        target = np.where(upper[act], hi[act], lo[act])
        A = Gs[act]
        reg = 1e-13
        kkt = sp.bmat([[Ps + reg * sp.eye(n), A.T], [A, -reg * sp.eye(act.size)]], format="csc")
        rhs = np.concatenate([-np.asarray(q, dtype=float), target])
        try:
            lu = spla.splu(kkt)
        except RuntimeError:
            return None
        sol = lu.solve(rhs)
        for _ in range(3):  # iterative refinement against the tiny regularisation
            sol = sol + lu.solve(rhs - _unreg_kkt(Ps, A) @ sol)
        x = sol[:n]
        y = sol[n:]
        r = Gs @ x
        viol_hi = (r > hi + tol) & ~upper
        viol_lo = (r < lo - tol) & ~lower
        wrong = np.zeros_like(upper)
        wrong[act] = (upper[act] & (y < -1e-9)) | (lower[act] & (y > 1e-9))
        if not viol_hi.any() and not viol_lo.any() and not wrong.any():
            return np.asarray(x)
        upper = (upper | viol_hi) & ~wrong
        lower = (lower | viol_lo) & ~wrong
    return None


def _unreg_kkt(P: sp.csc_matrix, A: sp.csr_matrix) -> sp.csc_matrix:
    import scipy.sparse as sp

    return sp.bmat([[P, A.T], [A, None]], format="csc")
