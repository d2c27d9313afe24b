"""First collision time of a trajectory with obstacles, and obstacle inflation.

Geometry the companion asks before it replans: when does the flown
trajectory first enter an obstacle inflated by the vehicle radius.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from planner_core.bezier import segments_at
from planner_core.problem import Polytope, Trajectory

INSIDE_EPS = 1e-9


def inflate(poly: Polytope, radius: float) -> Polytope:
    """The polytope grown by `radius` along each face normal (rows of A need not be unit)."""
    return Polytope(poly.A, poly.b + radius * np.linalg.norm(poly.A, axis=1))


def first_hit(traj: Trajectory, t_from: float, obstacles: Sequence[Polytope], radius: float, dt: float = 0.01) -> float | None:
    """Earliest sampled time >= t_from at which the trajectory enters an inflated obstacle."""
    if t_from >= traj.t_end or not obstacles:
        return None
    ts = np.arange(t_from, traj.t_end + dt, dt)
    inflated = [inflate(ob, radius) for ob in obstacles]
    # Sample only segments whose control-point hull (which holds the curve) is not wholly
    # beyond one plane of some inflated obstacle: same answer, a fraction of the evaluations
    # (this runs on the event loop, before the replan).
    seg = segments_at(traj.times, ts)
    near = np.zeros(traj.n_segments, dtype=bool)
    for ob in inflated:
        beyond = np.min(traj.control_points @ ob.A.T - ob.b, axis=1) > -INSIDE_EPS  # (S, P)
        near |= ~np.any(beyond, axis=1)
    ts = ts[near[seg]]
    if ts.size == 0:
        return None
    pts = traj.evaluate(ts)
    inside = np.zeros(len(ts), dtype=bool)
    for ob in inflated:
        inside |= ob.contains(pts, tol=-INSIDE_EPS)
    if not np.any(inside):
        return None
    return float(ts[int(np.argmax(inside))])


__all__ = ["first_hit", "inflate"]
