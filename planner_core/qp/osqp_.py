"""osqp: sparse ADMM (approximate), polished, then refined on its active set by
`refine_active_set` when polishing did not reach the requested accuracy.

Two ways in:
- `solve_osqp`: the general `solve_qp` signature (a `QPResult`, exact to `tol` or FAILED).
- `OsqpSolver`: the structure set up once (`setup`), then numbers changed (`update`),
  a warm start given (`warm_start`) and solved (`solve`) as often as needed; the
  answer is OSQP's own (primal and dual), for callers that refine it themselves.
OSQP's C code prints even with verbose off: every call into it is made with fd 1 silenced.
"""

from __future__ import annotations

import contextlib
import io
import os
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any, NamedTuple

import numpy as np

from planner_core.problem import FloatArray
from planner_core.qp.refine import max_violation, refine_active_set
from planner_core.qp.result import INF, Matrix, QPResult, QPStatus

NAME = "osqp"

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


class AdmmSolution(NamedTuple):
    """OSQP's answer as it came (`x`, `y` None when it gave no finite point); OPTIMAL means a finite
    point at the accuracy asked for, not an exact optimum."""

    x: FloatArray | None
    y: FloatArray | None
    iterations: int
    status: QPStatus


class OsqpSolver:
    """One OSQP workspace: the sparsity structure is factored once in `setup`; `update` changes
    numbers (q, limits, matrix values on the same pattern) without a new factorisation of the
    structure. P is given as the upper triangle (OSQP's form), limits as real infinities."""

    def __init__(self) -> None:
        import osqp

        self._osqp = osqp
        self._solver = osqp.OSQP()

    def setup(self, P: Matrix, q: FloatArray, G: Matrix, lo: FloatArray, hi: FloatArray, **settings: Any) -> None:
        with silenced_stdout():
            self._solver.setup(P, q, G, lo, hi, **settings)

    def update(self, **numbers: Any) -> None:
        """OSQP's `update` (q=, l=, u=, Px=, Ax=): same structure, new numbers."""
        with silenced_stdout():
            self._solver.update(**numbers)

    def warm_start(self, x: FloatArray | None = None, y: FloatArray | None = None) -> None:
        with silenced_stdout():
            if y is None:
                self._solver.warm_start(x=x)
            else:
                self._solver.warm_start(x=x, y=y)

    def solve(self) -> AdmmSolution:
        with silenced_stdout():
            res = self._solver.solve(raise_error=False)
        status = int(res.info.status_val)
        iters = int(res.info.iter)
        x = None if res.x is None or not np.all(np.isfinite(res.x)) else np.asarray(res.x)
        y = None if x is None else np.asarray(res.y)
        if status in {int(v) for v in _infeasible_codes(self._osqp)}:
            code = QPStatus.INFEASIBLE  # OSQP leaves no finite point then (its x is NaN)
        else:
            code = QPStatus.FAILED if x is None else QPStatus.OPTIMAL
        return AdmmSolution(x, y, iters, code)


def _infeasible_codes(osqp: Any) -> tuple[Any, Any]:
    return (osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE, osqp.SolverStatus.OSQP_PRIMAL_INFEASIBLE_INACCURATE)


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
    infeasible = _infeasible_codes(osqp)
    if status in {int(v) for v in infeasible}:
        return QPResult(QPStatus.INFEASIBLE, None, iters, time.perf_counter() - t0, NAME)
    if res.x is None or not np.all(np.isfinite(res.x)):
        return QPResult(QPStatus.FAILED, None, iters, time.perf_counter() - t0, NAME)
    x = np.asarray(res.x, dtype=float)
    y = np.asarray(res.y, dtype=float)
    refined = False
    if max_violation(Gs, x, lo_c, hi_c) > tol:
        xr = refine_active_set(Ps + sp.triu(Ps, 1).T, q, Gs, lo_c, hi_c, x, y, tol=tol)
        if xr is None:
            return QPResult(QPStatus.FAILED, None, iters, time.perf_counter() - t0, NAME)
        x, refined = xr, True
    return QPResult(QPStatus.OPTIMAL, x, iters, time.perf_counter() - t0, NAME, refined)
