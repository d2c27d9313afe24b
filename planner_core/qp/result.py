"""What every QP backend hands back: a status code, the point found, and its costs.

Problem form everywhere: minimise 0.5 x'Px + q'x subject to lo <= G x <= hi
(no equality rows: the jet form has none). Infinite limits are clipped to
`INF` (1e30), which every backend reads as "no bound".
"""

from __future__ import annotations

import enum
import sys
from dataclasses import dataclass
from typing import TYPE_CHECKING, TypeAlias

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


def issparse(a: object) -> bool:
    """scipy.sparse.issparse, without importing scipy.sparse (nothing is sparse before it is)."""
    sparse = sys.modules.get("scipy.sparse")
    return sparse is not None and bool(sparse.issparse(a))


def dense(a: Matrix) -> FloatArray:
    """A C-contiguous float64 copy (or view) of a dense or sparse matrix."""
    if issparse(a):
        return np.asarray(a.toarray(), dtype=np.float64)  # type: ignore[union-attr]
    return np.ascontiguousarray(a, dtype=float)
