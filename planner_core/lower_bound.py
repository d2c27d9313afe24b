"""What no trajectory within the bounds can beat: a proven lower bound on the flight time
through given waypoints (in order), for any curve, not only this planner's.

Two bounds; the flight takes at least the larger (`FlightTimeBound.value`):

- `per_segment`: sum_j max_axis |dW_j| / v_axis (each leg at full speed on its slowest axis,
  turns free). Issue 12 states its mission target against this one.
- `turning`: per axis, the coordinates of the waypoints are visited in order, so between two
  of that axis' turning points the curve stops on that axis. Choose, in order, the time of the
  curve's extreme beyond each turning point (the latest extreme of the stretch from the previous
  one to the next turning waypoint): it is interior, so v = 0 there, while the acceleration is
  free (its sign only). Each run D between two stops then takes at least the larger of
    * v/a:  D <= int min(V, A t, A (T - t)) dt,
    * a/j:  D = int_0^{T/2} u (a(T/2 - u) - a(T/2 + u)) du <= int_0^{T/2} u min(2A, 2J u) du
            (|a| <= A, and a is J-Lipschitz; equality for a = clip(J (T/2 - t), -A, A)),
  and the axis' runs add up. Snap and the corridors are left out, so it stays a lower bound;
  the boundary accelerations are left free, so a real rest start (a = 0) only makes it looser.

V, A, J are each axis' larger bound magnitude (asymmetric bounds: the side that helps, so the
bound stays valid); a horizontal norm bound r caps x and y at r, and `per_segment` also counts
each leg's horizontal distance at r. Pure numpy; nothing here plans.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from planner_core.problem import Bounds, FloatArray


@dataclass(frozen=True)
class FlightTimeBound:
    per_segment: float  # sum_j max_axis |dW_j| / v_max
    turning: float  # the slowest axis' runs between turning points under v, a, j
    axis: int  # the axis of `turning`

    @property
    def value(self) -> float:
        return max(self.per_segment, self.turning)


def run_time(distance: FloatArray | float, v: float, a: float, j: float) -> FloatArray:
    """Least time to move `distance` along one axis from v = 0 to v = 0 (boundary accelerations
    free) under |v| <= v, |a| <= a, |jerk| <= j: the larger of the v/a and the a/j bounds."""
    d = np.abs(np.asarray(distance, dtype=float))
    t = np.zeros_like(d)
    if np.isfinite(a):
        t = 2.0 * np.sqrt(d / a)
        if np.isfinite(v):
            t = np.where(d >= v * v / a, d / v + v / a, t)
    elif np.isfinite(v):
        t = d / v
    if np.isfinite(j):
        if np.isfinite(a):
            short = d <= 2.0 * a**3 / (3.0 * j * j)
            t_aj = np.where(short, np.cbrt(12.0 * d / j), 2.0 * np.sqrt((d + a**3 / (3.0 * j * j)) / a))
        else:
            t_aj = np.cbrt(12.0 * d / j)
        t = np.maximum(t, t_aj)
    return np.asarray(t, dtype=float)


def axis_runs(x: FloatArray) -> FloatArray:
    """Lengths of the monotone runs of the coordinate sequence x (zero steps merged away)."""
    dx = np.diff(np.asarray(x, dtype=float))
    dx = dx[np.abs(dx) > 1e-12]
    if dx.size == 0:
        return np.zeros(0)
    turn = np.flatnonzero(np.sign(dx[1:]) != np.sign(dx[:-1])) + 1
    return np.abs(np.add.reduceat(dx, np.concatenate([[0], turn])))


def flight_time_lower_bound(waypoints: FloatArray, bounds: Bounds) -> FlightTimeBound:
    """The proven lower bound for a flight from rest at waypoints[0] through every waypoint, in
    order, to rest at the last (see the module docstring)."""
    w = np.asarray(waypoints, dtype=float)
    lo, hi = bounds.axis_limits()  # a horizontal norm bound r limits |x| and |y| to r too
    mag = np.maximum(hi, -lo)  # (4, 3)
    step = np.diff(w, axis=0)
    per_leg = np.max(np.abs(step) / mag[0], axis=1)
    if bounds.has_norm:  # the horizontal distance at the horizontal speed bound
        per_leg = np.maximum(per_leg, np.hypot(step[:, 0], step[:, 1]) / bounds.horizontal[0])
    per_segment = float(np.sum(per_leg)) if len(w) > 1 else 0.0
    best, axis = 0.0, 0
    for ax in range(w.shape[1]):
        t = float(np.sum(run_time(axis_runs(w[:, ax]), *(float(mag[k, ax]) for k in range(3)))))
        if t > best:
            best, axis = t, ax
    return FlightTimeBound(per_segment, best, axis)
