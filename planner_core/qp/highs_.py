"""HiGHS (through scipy.optimize.linprog): the one LP the planner solves, the elastic
relaxation that names the constraints to blame for an infeasible QP."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from planner_core.problem import FloatArray

NAME = "highs"


@dataclass(frozen=True)
class LPResult:
    ok: bool  # solved to optimality (linprog status 0) with a point
    x: FloatArray | None
    status: int  # linprog's own code: 0 optimal, 1 iteration limit, 2 infeasible, 3 unbounded, 4 other


def solve_lp(
    c: FloatArray, A_ub: FloatArray, b_ub: FloatArray, bounds: Sequence[tuple[float | None, float | None]]
) -> LPResult:
    """min c'x s.t. A_ub x <= b_ub and the per-variable `bounds` (None: unbounded)."""
    from scipy.optimize import linprog

    res = linprog(c, A_ub=A_ub, b_ub=b_ub, bounds=list(bounds), method="highs")
    x = None if res.x is None else np.asarray(res.x)
    return LPResult(res.status == 0 and x is not None, x, int(res.status))
