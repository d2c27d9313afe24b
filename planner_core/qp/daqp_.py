"""daqp: dense active-set, exact on its active set; the default for the small per-waypoint QPs.

Two ways in:
- `solve_daqp`: the general `solve_qp` signature (any matrix, limits clipped, a `QPResult`).
- `DaqpSolver`: a reusable handle for hot loops that build their arrays already in daqp's
  form (C-contiguous float64, limits within +-INF, an int32 `sense` array that daqp writes
  its active set back into). It binds `daqp.solve` once and the settings once, and passes
  the arrays through untouched: the conversions and result object of `solve_daqp` cost as
  much as the solve itself at ~50 unknowns.
"""

from __future__ import annotations

import time
from collections.abc import Callable
from typing import Any, NamedTuple

import numpy as np

from planner_core.problem import FloatArray
from planner_core.qp.result import INF, Matrix, QPResult, QPStatus, dense

NAME = "daqp"

# daqp's exit flags: 1 optimal, 2 soft-optimal; -1 infeasible; anything else a failure
_STATUS: dict[int, QPStatus] = {1: QPStatus.OPTIMAL, 2: QPStatus.OPTIMAL, -1: QPStatus.INFEASIBLE}

# sense codes (daqp's own): 0 an inequality row, 5 an equality row (active, immutable)
SENSE_INEQUALITY = 0
SENSE_EQUALITY = 5


def status_of(exitflag: int) -> QPStatus:
    return _STATUS.get(int(exitflag), QPStatus.FAILED)


class DenseSolution(NamedTuple):
    """daqp's answer as it came: `x` and the multipliers `lam` are daqp's own arrays."""

    x: FloatArray
    lam: FloatArray
    exitflag: int
    status: QPStatus

    @property
    def ok(self) -> bool:
        return self.status is QPStatus.OPTIMAL


class DaqpSolver:
    """daqp bound once with fixed settings (e.g. `primal_tol`, `iter_limit`, `eps_prox`); only the
    settings given are passed, so the others stay daqp's defaults."""

    __slots__ = ("_settings", "_solve")

    def __init__(self, **settings: float) -> None:
        import daqp

        self._solve: Callable[..., Any] = daqp.solve
        self._settings = settings

    def solve(
        self, H: FloatArray, f: FloatArray, A: FloatArray, upper: FloatArray, lower: FloatArray, sense: Any
    ) -> DenseSolution:
        """min 0.5 x'Hx + f'x s.t. lower <= A x <= upper; `sense` (int32, one per row) is read
        and written back by daqp."""
        x, _, flag, info = self._solve(H, f, A, upper, lower, sense, **self._settings)
        return DenseSolution(x, info["lam"], flag, _STATUS.get(flag, QPStatus.FAILED))


def solve_daqp(P: Matrix, q: FloatArray, G: Matrix, lo: FloatArray, hi: FloatArray, *, tol: float = 1e-10) -> QPResult:
    import daqp

    H = dense(P)
    A = dense(G)
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
        return QPResult(QPStatus.OPTIMAL, np.asarray(x, dtype=float), iters, elapsed, NAME)
    if exitflag == -1:
        return QPResult(QPStatus.INFEASIBLE, None, iters, elapsed, NAME)
    return QPResult(QPStatus.FAILED, None, iters, elapsed, NAME)
