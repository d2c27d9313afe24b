"""One typed interface over the QP backends (qpsolvers' habit: one module per backend).

Problem form everywhere: minimise 0.5 x'Px + q'x subject to lo <= G x <= hi
(no equality rows: the jet form has none). Infinite limits are clipped to
`INF` (1e30), which both backends read as "no bound".

- `daqp_` (`daqp`): dense active-set (exact on its active set); default for the small
  per-waypoint QPs. `DaqpSolver` is its reusable handle for hot loops.
- `osqp_` (`osqp`): sparse ADMM (approximate), polished, then refined on its active set
  by `refine_active_set` when polishing did not reach the requested accuracy.
  `OsqpSolver` keeps one workspace (setup once, update numbers, warm start, solve).
- `highs_`: the one LP (scipy's HiGHS), for the infeasibility diagnosis.

The solver libraries are imported in these modules only (tests/planner/test_imports.py).
Adding a backend: one module with a `solve_<name>` of `solve_qp`'s signature, one line in
`_SOLVERS`.
"""

from __future__ import annotations

from collections.abc import Callable

from planner_core.problem import FloatArray
from planner_core.qp.daqp_ import (
    SENSE_EQUALITY,
    SENSE_INEQUALITY,
    DaqpSolver,
    DenseSolution,
    solve_daqp,
)
from planner_core.qp.highs_ import LPResult, solve_lp
from planner_core.qp.osqp_ import AdmmSolution, OsqpSolver, silenced_stdout, solve_osqp
from planner_core.qp.refine import refine_active_set
from planner_core.qp.result import INF, Matrix, QPResult, QPStatus, issparse

__all__ = [
    "BACKENDS",
    "INF",
    "SENSE_EQUALITY",
    "SENSE_INEQUALITY",
    "AdmmSolution",
    "DaqpSolver",
    "DenseSolution",
    "LPResult",
    "Matrix",
    "OsqpSolver",
    "QPResult",
    "QPStatus",
    "issparse",
    "refine_active_set",
    "silenced_stdout",
    "solve_daqp",
    "solve_lp",
    "solve_osqp",
    "solve_qp",
]

_SOLVERS: dict[str, Callable[..., QPResult]] = {"daqp": solve_daqp, "osqp": solve_osqp}
BACKENDS = tuple(_SOLVERS)


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
    solver = _SOLVERS.get(backend)
    if solver is None:
        raise ValueError(f"backend: unknown QP backend {backend!r} (expected one of {BACKENDS})")
    return solver(P, q, G, lo, hi, tol=tol)
