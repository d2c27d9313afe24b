"""One typed interface over the QP backends (qpsolvers style, one function per backend).

Problem form everywhere: minimise 0.5 x'Px + q'x subject to lo <= G x <= hi
(no equality rows: the jet form has none). Infinite limits are clipped to
`INF` (1e30), which both backends read as "no bound".

- `daqp`: dense active-set (exact on its active set); default for the small
  per-waypoint QPs.
- `osqp`: sparse ADMM (approximate), polished, then refined on its active set
  by `refine_active_set` when polishing did not reach the requested accuracy.
"""

from __future__ import annotations

import contextlib
import enum
import io
import os
import sys
import threading
import time
from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, TypeAlias

import numpy as np

from planner_core.problem import FloatArray

if TYPE_CHECKING:
    # imported where used: scipy.sparse costs ~0.1 s of start-up that a dense daqp solve never needs
    import scipy.sparse as sp

INF = 1e30
Matrix: TypeAlias = "FloatArray | sp.spmatrix | sp.sparray"


class QPStatus(enum.Enum):
    OPTIMAL = "optimal"
    INFEASIBLE = "infeasible"
    FAILED = "failed"


@dataclass(frozen=True)
class QPResult:
    status: QPStatus
    x: FloatArray | None
    iterations: int
    solve_time: float  # seconds, wall clock around the backend call
    backend: str
    refined: bool = False

    @property
    def ok(self) -> bool:
        return self.status is QPStatus.OPTIMAL and self.x is not None


BACKENDS = ("daqp", "osqp")


def solve_qp(
    P: Matrix,
    q: FloatArray,
    G: Matrix,
    lo: FloatArray,
    hi: FloatArray,
    backend: str = "daqp",
    *,
    tol: float = 1e-10,
) -> QPResult:
    """Solve one QP with the named backend; `tol` is the primal accuracy asked for."""
    if backend == "daqp":
        return solve_daqp(P, q, G, lo, hi, tol=tol)
    if backend == "osqp":
        return solve_osqp(P, q, G, lo, hi, tol=tol)
    raise ValueError(f"backend: unknown QP backend {backend!r} (expected one of {BACKENDS})")


def issparse(a: object) -> bool:
    """scipy.sparse.issparse, without importing scipy.sparse (nothing is sparse before it is)."""
    sparse = sys.modules.get("scipy.sparse")
    return sparse is not None and bool(sparse.issparse(a))


def _dense(a: Matrix) -> FloatArray:
    if issparse(a):
        return np.asarray(a.toarray(), dtype=np.float64)  # type: ignore[union-attr]
    return np.ascontiguousarray(a, dtype=float)


def solve_daqp(P: Matrix, q: FloatArray, G: Matrix, lo: FloatArray, hi: FloatArray, *, tol: float = 1e-10) -> QPResult:
    import daqp

    H = _dense(P)
    A = _dense(G)
    n_rows = A.shape[0]
    bu = np.ascontiguousarray(np.clip(hi, -INF, INF), dtype=float)
    bl = np.ascontiguousarray(np.clip(lo, -INF, INF), dtype=float)
    sense = np.zeros(n_rows, dtype=np.int32)
    t0 = time.perf_counter()
    x, _, exitflag, info = daqp.solve(
        H, np.ascontiguousarray(q, dtype=float), A, bu, bl, sense, primal_tol=tol, iter_limit=2000
    )
    elapsed = time.perf_counter() - t0
    iters = int(info.get("iterations", 0)) if isinstance(info, dict) else 0
    if exitflag == 1 or exitflag == 2:  # 2: soft-optimal, not used here but harmless
        return QPResult(QPStatus.OPTIMAL, np.asarray(x, dtype=float), iters, elapsed, "daqp")
    if exitflag == -1:
        return QPResult(QPStatus.INFEASIBLE, None, iters, elapsed, "daqp")
    return QPResult(QPStatus.FAILED, None, iters, elapsed, "daqp")


_STDOUT_LOCK = threading.Lock()


@contextlib.contextmanager
def silenced_stdout() -> Iterator[None]:
    """Silence fd 1 around a native call: OSQP's C code prints even with verbose off."""
    with _STDOUT_LOCK:
        with contextlib.suppress(AttributeError, ValueError):
            sys.stdout.flush()
        saved = os.dup(1)
        devnull = os.open(os.devnull, os.O_WRONLY)
        try:
            os.dup2(devnull, 1)
            # OSQP's Python build prints through PySys_WriteStdout, i.e. sys.stdout
            with contextlib.redirect_stdout(io.StringIO()):
                yield
        finally:
            _flush_c_stdio()  # C printf output sits in stdio's buffer until flushed
            os.dup2(saved, 1)
            os.close(saved)
            os.close(devnull)


def _flush_c_stdio() -> None:
    global _LIBC
    if _LIBC is None:
        import ctypes

        _LIBC = ctypes.CDLL(None)
    _LIBC.fflush(None)


_LIBC: Any = None


def solve_osqp(P: Matrix, q: FloatArray, G: Matrix, lo: FloatArray, hi: FloatArray, *, tol: float = 1e-10) -> QPResult:
    import osqp
    import scipy.sparse as sp

    Ps = sp.triu(sp.csc_matrix(P), format="csc")
    Gs = sp.csc_matrix(G)
    # OSQP wants real infinities (it maps them to its own OSQP_INFTY internally)
    lo_c = np.where(lo <= -INF, -np.inf, lo)
    hi_c = np.where(hi >= INF, np.inf, hi)
    t0 = time.perf_counter()
    solver = osqp.OSQP()
    with silenced_stdout():
        solver.setup(
            Ps, np.asarray(q, dtype=float), Gs, lo_c, hi_c,
            verbose=False, polishing=True, eps_abs=1e-6, eps_rel=1e-6,
            max_iter=20000, polish_refine_iter=10,
        )
        res = solver.solve(raise_error=False)
    status = int(res.info.status_val)
    iters = int(res.info.iter)
    infeasible = (osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE, osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE_INACCURATE)
    if status in {int(v) for v in infeasible}:
        return QPResult(QPStatus.INFEASIBLE, None, iters, time.perf_counter() - t0, "osqp")
    if res.x is None or not np.all(np.isfinite(res.x)):
        return QPResult(QPStatus.FAILED, None, iters, time.perf_counter() - t0, "osqp")
    x = np.asarray(res.x, dtype=float)
    y = np.asarray(res.y, dtype=float)
    refined = False
    if _max_violation(Gs, x, lo_c, hi_c) > tol:
        xr = refine_active_set(Ps + sp.triu(Ps, 1).T, q, Gs, lo_c, hi_c, x, y, tol=tol)
        if xr is None:
            return QPResult(QPStatus.FAILED, None, iters, time.perf_counter() - t0, "osqp")
        x, refined = xr, True
    return QPResult(QPStatus.OPTIMAL, x, iters, time.perf_counter() - t0, "osqp", refined)


def _max_violation(G: Matrix, x: FloatArray, lo: FloatArray, hi: FloatArray) -> float:
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
