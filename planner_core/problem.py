"""Frozen value types shared by every planner module.

Conventions (used everywhere in planner_core):
- positions are rows of shape (3,) in one Cartesian frame (the caller's);
- a *jet* is an array of shape (5, 3): rows are position, velocity,
  acceleration, jerk and snap at one instant;
- bounds are arrays of shape (4, 3): row k-1 bounds the k-th derivative
  (k = 1..4) per axis; +-inf means unbounded; optionally a bound on the norm of
  the horizontal (x, y) part per order (`Bounds.horizontal`, (4,));
- a trajectory of m waypoints has m-1 Bézier segments of degree 9, stored as
  control points of shape (m-1, 10, 3).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

# the Bézier facts live with the Bernstein maths (bezier.py imports nothing of planner_core)
from planner_core.bezier import DEGREE as DEGREE
from planner_core.bezier import JET_ORDER as JET_ORDER
from planner_core.bezier import FloatArray as FloatArray
from planner_core.bezier import evaluate_trajectory, trajectory_jet

N_CTRL = DEGREE + 1
ORDER_NAMES = ("position", "velocity", "acceleration", "jerk", "snap")


def rest_jet(position: FloatArray) -> FloatArray:
    """A jet at rest at `position` (all derivatives zero)."""
    jet = np.zeros((JET_ORDER, 3))
    jet[0] = np.asarray(position, dtype=float)
    return jet


POLYGON_SIDES = 16  # sides of the polygon that certifies a horizontal norm bound (loses 1 - cos(pi/16) = 1.9 %)


def _no_norm() -> FloatArray:
    return np.full(4, np.inf)


@dataclass(frozen=True)
class Bounds:
    """Bounds on derivatives 1..4: a per-order, per-axis box, and optionally a bound on the norm
    of the horizontal (x, y) part, per order (`horizontal`, np.inf = none). Both apply.

    The norm bound r is certified on a regular polygon of `sides` sides inscribed in the disc of
    radius r (vertices on the circle, on the axes when 4 divides `sides`): half-planes
    |n_i . (x, y)| <= r cos(pi / sides), linear, so every QP stays a QP, and a point inside the
    polygon is inside the disc (docs/bounds.md). Vertical limits are the box's z row (up and
    down apart: asymmetric lo / hi)."""

    lo: FloatArray  # (4, 3)
    hi: FloatArray  # (4, 3)
    horizontal: FloatArray = field(default_factory=_no_norm)  # (4,) norm bound per order 1..4
    sides: int = POLYGON_SIDES

    def __post_init__(self) -> None:
        h = np.asarray(self.horizontal, dtype=float)
        if h.shape != (4,):
            raise ValueError(f"horizontal: expected 4 norm bounds (orders 1..4), got shape {h.shape}")
        if np.any(np.isnan(h)) or np.any(h <= 0.0):
            raise ValueError(f"horizontal: norm bounds must be > 0 (np.inf for none), got {h.tolist()}")
        if isinstance(self.sides, bool) or not isinstance(self.sides, int | np.integer) or self.sides < 4 \
                or self.sides % 2:
            raise ValueError(f"sides: the certifying polygon needs an even number >= 4 of sides, got {self.sides}")
        object.__setattr__(self, "horizontal", h)
        object.__setattr__(self, "sides", int(self.sides))

    @staticmethod
    def symmetric(velocity: float, acceleration: float, jerk: float, snap: float) -> Bounds:
        hi = np.repeat(np.array([[velocity], [acceleration], [jerk], [snap]], dtype=float), 3, axis=1)
        return Bounds(lo=-hi, hi=hi.copy())

    @staticmethod
    def unbounded() -> Bounds:
        hi = np.full((4, 3), np.inf)
        return Bounds(lo=-hi, hi=hi.copy())

    @staticmethod
    def vehicle(
        horizontal: Sequence[float],
        up: Sequence[float],
        down: Sequence[float],
        *,
        z_up: bool = False,
        box: Bounds | None = None,
        sides: int = POLYGON_SIDES,
    ) -> Bounds:
        """A vehicle's bounds as autopilots state them: the horizontal norm of velocity,
        acceleration, jerk and snap (`horizontal`, 4 numbers, np.inf = none), and the vertical
        magnitudes going up and going down (`up`, `down`, 4 positive numbers each). The frame is
        NED (z down: up is -z) unless `z_up`. `box` adds per-axis bounds (both apply; its z row
        is intersected with up / down)."""
        hor = np.asarray(horizontal, dtype=float)
        u = np.asarray(up, dtype=float)
        d = np.asarray(down, dtype=float)
        if hor.shape != (4,):
            raise ValueError(f"horizontal: expected 4 norm bounds (orders 1..4), got {hor.tolist()}")
        for name, v in (("up", u), ("down", d)):
            if v.shape != (4,) or np.any(np.isnan(v)) or np.any(v <= 0.0):
                raise ValueError(f"{name}: expected 4 magnitudes > 0 (np.inf for none), got {v.tolist()}")
        base = box if box is not None else Bounds.unbounded()
        lo, hi = np.array(base.lo, dtype=float), np.array(base.hi, dtype=float)
        z_lo, z_hi = (-d, u) if z_up else (-u, d)
        lo[:, 2] = np.maximum(lo[:, 2], z_lo)
        hi[:, 2] = np.minimum(hi[:, 2], z_hi)
        norm = np.minimum(hor, base.horizontal)
        return Bounds(lo=lo, hi=hi, horizontal=norm, sides=sides)

    @property
    def has_norm(self) -> bool:
        """A horizontal norm bound on some order."""
        return bool(np.any(np.isfinite(self.horizontal)))

    @property
    def polygon_radius(self) -> FloatArray:
        """(4,) the certified half-plane limit r cos(pi / sides) per order (inf: none)."""
        return np.asarray(self.horizontal * np.cos(np.pi / self.sides))

    def axis_limits(self) -> tuple[FloatArray, FloatArray]:
        """(lo, hi) of the box intersected with what the norm implies on x and y (|x|, |y| <= r):
        the per-axis limits for estimates that work axis by axis (time allocation, stop times,
        lower bounds). Never looser than either bound."""
        lo, hi = np.array(self.lo, dtype=float), np.array(self.hi, dtype=float)
        if self.has_norm:
            r = self.horizontal[:, None]
            lo[:, :2] = np.maximum(lo[:, :2], -r)
            hi[:, :2] = np.minimum(hi[:, :2], r)
        return lo, hi

    def same_as(self, other: Bounds) -> bool:
        """Equal limits (box, norm and polygon), bit for bit."""
        return bool(np.array_equal(self.lo, other.lo) and np.array_equal(self.hi, other.hi)
                    and np.array_equal(self.horizontal, other.horizontal) and self.sides == other.sides)

    def key(self) -> bytes:
        """Bytes that identify the limits (a cache key)."""
        return np.concatenate((self.lo, self.hi, self.horizontal, [float(self.sides)]), axis=None).tobytes()

    def scaled(self, factor: float) -> Bounds:
        return Bounds(lo=self.lo * factor, hi=self.hi * factor, horizontal=self.horizontal * factor,
                      sides=self.sides)


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
        return evaluate_trajectory(self, np.asarray(t, dtype=float), order)

    def jet(self, t: float) -> FloatArray:
        """Position, velocity, acceleration, jerk and snap at time t, shape (5, 3)."""
        return trajectory_jet(self, float(t))
