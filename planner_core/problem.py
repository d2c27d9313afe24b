"""Frozen value types shared by every planner module.

Conventions (used everywhere in planner_core):
- positions are rows of shape (3,) in one Cartesian frame (the caller's);
- a *jet* is an array of shape (5, 3): rows are position, velocity,
  acceleration, jerk and snap at one instant;
- bounds are arrays of shape (4, 3): row k-1 bounds the k-th derivative
  (k = 1..4) per axis; +-inf means unbounded;
- a trajectory of m waypoints has m-1 Bézier segments of degree 9, stored as
  control points of shape (m-1, 10, 3).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

DEGREE = 9
N_CTRL = DEGREE + 1
JET_ORDER = 5  # position .. snap
ORDER_NAMES = ("position", "velocity", "acceleration", "jerk", "snap")


def rest_jet(position: FloatArray) -> FloatArray:
    """A jet at rest at `position` (all derivatives zero)."""
    jet = np.zeros((JET_ORDER, 3))
    jet[0] = np.asarray(position, dtype=float)
    return jet


@dataclass(frozen=True)
class Bounds:
    """Per-order, per-axis box bounds on derivatives 1..4."""

    lo: FloatArray  # (4, 3)
    hi: FloatArray  # (4, 3)

    @staticmethod
    def symmetric(velocity: float, acceleration: float, jerk: float, snap: float) -> Bounds:
        hi = np.repeat(np.array([[velocity], [acceleration], [jerk], [snap]], dtype=float), 3, axis=1)
        return Bounds(lo=-hi, hi=hi.copy())

    @staticmethod
    def unbounded() -> Bounds:
        hi = np.full((4, 3), np.inf)
        return Bounds(lo=-hi, hi=hi.copy())

    def scaled(self, factor: float) -> Bounds:
        return Bounds(lo=self.lo * factor, hi=self.hi * factor)


@dataclass(frozen=True)
class Polytope:
    """Convex region {x : A x <= b} in R^3."""

    A: FloatArray  # (k, 3)
    b: FloatArray  # (k,)

    def contains(self, points: FloatArray, tol: float = 0.0) -> NDArray[np.bool_]:
        pts = np.atleast_2d(points)
        return np.asarray(np.all(pts @ self.A.T <= self.b + tol, axis=-1))

    def violation(self, points: FloatArray) -> float:
        """Largest A x - b over the points (<= 0 means inside)."""
        pts = np.atleast_2d(points)
        if self.A.shape[0] == 0:
            return -np.inf
        return float(np.max(pts @ self.A.T - self.b))


@dataclass(frozen=True)
class Problem:
    """A planning problem in the jet form of method.md.

    `corridors` is None (no safety constraints) or one entry per segment, each
    a Polytope or None (that segment unconstrained).
    """

    waypoints: FloatArray  # (m, 3)
    times: FloatArray  # (m,), strictly increasing
    bounds: Bounds
    initial: FloatArray  # (5, 3) jet at waypoint 0; row 0 equals waypoints[0]
    final: FloatArray  # (5, 3) jet at waypoint m-1; row 0 equals waypoints[-1]
    corridors: tuple[Polytope | None, ...] | None = None

    @property
    def m(self) -> int:
        return int(self.waypoints.shape[0])

    @property
    def durations(self) -> FloatArray:
        return np.diff(self.times)

    def corridor(self, segment: int) -> Polytope | None:
        if self.corridors is None:
            return None
        return self.corridors[segment]

    @staticmethod
    def from_waypoints(
        waypoints: FloatArray | list[list[float]],
        durations: FloatArray | list[float],
        bounds: Bounds,
        corridors: tuple[Polytope | None, ...] | None = None,
        initial: FloatArray | None = None,
        final: FloatArray | None = None,
        t0: float = 0.0,
    ) -> Problem:
        wps = np.asarray(waypoints, dtype=float)
        times = t0 + np.concatenate([[0.0], np.cumsum(np.asarray(durations, dtype=float))])
        init = rest_jet(wps[0]) if initial is None else np.asarray(initial, dtype=float)
        fin = rest_jet(wps[-1]) if final is None else np.asarray(final, dtype=float)
        return Problem(wps, times, bounds, init, fin, corridors)


@dataclass(frozen=True)
class Trajectory:
    """A C^4 piecewise Bézier curve of degree 9 (the planner's output)."""

    times: FloatArray  # (m,) segment boundary times
    control_points: FloatArray  # (m-1, 10, 3)
    corridors: tuple[Polytope | None, ...] | None = None
    stats: dict[str, Any] = field(default_factory=dict, compare=False)

    @property
    def n_segments(self) -> int:
        return int(self.control_points.shape[0])

    @property
    def t0(self) -> float:
        return float(self.times[0])

    @property
    def t_end(self) -> float:
        return float(self.times[-1])

    @property
    def waypoints(self) -> FloatArray:
        return np.concatenate([self.control_points[:, 0, :], self.control_points[-1:, -1, :]])

    def evaluate(self, t: FloatArray | float, order: int = 0) -> FloatArray:
        """Derivative `order` (0..9) at times t (clamped to the trajectory span)."""
        from planner_core.bezier import evaluate_trajectory

        return evaluate_trajectory(self, np.asarray(t, dtype=float), order)

    def jet(self, t: float) -> FloatArray:
        """Position, velocity, acceleration, jerk and snap at time t, shape (5, 3)."""
        from planner_core.bezier import trajectory_jet

        return trajectory_jet(self, float(t))
