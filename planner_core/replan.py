"""Local replanning (paper section 3.1): re-solve only the jets a change touches.

A trajectory's segments are fixed by the jets at their two ends, so a change
near waypoint j only needs new jets near j; every other segment is copied
bit-for-bit from the current trajectory (its control points, never rebuilt
from recovered jets). Seed sets follow method.md ("Replanning"):

- move W_j                  -> jet j (neighbours fixed, both segments fully constrained);
- duration of segment s     -> jets s, s+1;
- corridor of segment s     -> jets s, s+1, but only when the current segment
                               leaves the new corridor (otherwise nothing changes);
- insert W_i                -> the new jet i; remove W_i -> the two neighbours;
- append                    -> the old terminal jet and the new interior jets.

Jets that are fixed by the problem (the initial and terminal state) and jets
at or before a `from_time` split are never free. When the seed QP is
infeasible the free set grows by one neighbour on each side per step
(`max_widen` steps), then the durations of the touched segments are
stretched (`max_stretch` times, later waypoints shift in time; their control
points do not change).

The work is O(size of the change): the QP runs on a window sub-problem, only
rebuilt segments are certified (hull of bounds and corridors, plus C^4
continuity against their kept neighbours); the only O(m) work is numpy array
copies.

This module holds the entry point (`replan`), the splits at `from_time` and `jets_of`; the
working state, the options and the result are in `planner_core.replan_work`, the solving and
the widen/stretch search in `planner_core.replan_solve` (the names are importable from here,
as before).
"""

from __future__ import annotations

import time
from collections.abc import Sequence
from typing import Any

import numpy as np

from planner_core.changes import ChangeError, ChangeSet, Edit, as_change_set, parse_change
from planner_core.problem import JET_ORDER, FloatArray, Problem, Trajectory
from planner_core.replan_solve import CONTINUITY_TOL as CONTINUITY_TOL
from planner_core.replan_solve import JOINT_MAX as JOINT_MAX
from planner_core.replan_solve import search
from planner_core.replan_work import TIME_EPS as TIME_EPS
from planner_core.replan_work import (
    Environment,
    Infeasible,
    ReplanOptions,
    ReplanResult,
    ReplanWork,
    apply_edits,
    rebuild_corridors,
    split_index,
)
from planner_core.result import PlanStatus
from planner_core.trajectory import split_at

__all__ = [
    "ChangeError",
    "ChangeSet",
    "Environment",
    "ReplanOptions",
    "ReplanResult",
    "parse_change",
    "replan",
    "split_inside",
    "split_problem_at",
]


# --- splitting ---------------------------------------------------------------


def split_inside(traj: Trajectory, t: float) -> Trajectory:
    """The same curve with one more segment boundary at t, strictly inside the span.

    The surgery is `planner_core.trajectory.split_at`; this only refuses the cases where
    no new boundary would be made: ValueError when t is not strictly inside the span or
    lies within TIME_EPS of an existing waypoint time.
    """
    t = float(t)
    if not traj.times[0] < t < traj.times[-1]:
        raise ValueError(f"t: {t} is not inside the trajectory span ({traj.t0}, {traj.t_end})")
    k, needed = split_index(traj.times, t)
    if not needed:
        raise ValueError(f"t: {t} coincides with the time of waypoint {k}")
    new, at = split_at(traj, t)
    assert at == k and new is not traj  # |t - times| > TIME_EPS: always a fresh boundary at k
    return new


def split_problem_at(problem: Problem, traj: Trajectory, t: float) -> tuple[Problem, Trajectory, int]:
    """Split both at t; returns (problem, trajectory, index of the split waypoint).

    The split waypoint's jet is the trajectory's own jet there, pinned: replan
    never frees it, so the piece being flown does not change.
    """
    new_traj = split_inside(traj, t)
    k, _ = split_index(traj.times, float(t))
    s = k - 1
    wps = np.concatenate((problem.waypoints[:k], new_traj.control_points[k, :1], problem.waypoints[k:]))
    corridors = None if problem.corridors is None else (*problem.corridors[: s + 1], *problem.corridors[s:])
    new_problem = Problem(wps, new_traj.times.copy(), problem.bounds, problem.initial, problem.final, corridors)
    return new_problem, new_traj, k


def replan(
    problem: Problem,
    traj: Trajectory,
    change: ChangeSet | Edit | Sequence[Edit],
    *,
    options: ReplanOptions | None = None,
) -> ReplanResult:
    """Apply `change` and re-solve only the affected jets; see the module docstring.

    Raises ChangeError for invalid changes (bad index, field); infeasibility is
    a result (status INFEASIBLE, trajectory None, the input problem).
    """
    t_start = time.perf_counter()
    given = problem
    opts = options or ReplanOptions()
    cs = as_change_set(change)
    if traj.n_segments != problem.m - 1:
        raise ChangeError("trajectory", f"has {traj.n_segments} segments, the problem {problem.m - 1}")
    if traj.times is not problem.times and not (
        traj.times.shape == problem.times.shape and bool((traj.times == problem.times).all())
    ):
        # the planner may have stretched durations: the trajectory's times are what is flown
        if not bool((traj.times[1:] > traj.times[:-1]).all()):
            raise ChangeError("trajectory", "times are not strictly increasing")
        problem = Problem(problem.waypoints, traj.times.copy(), problem.bounds, problem.initial, problem.final,
                          problem.corridors)
    lock, split = 0, False
    if cs.from_time is not None:
        t = float(cs.from_time)
        if t >= problem.times[-1] - TIME_EPS:
            lock = problem.m - 1
        elif t > problem.times[0] + TIME_EPS:
            lock, split = split_index(problem.times, t)
            if split:
                problem, traj, lock = split_problem_at(problem, traj, t)
    if opts.neighbours is not None:
        from dataclasses import replace

        opts = replace(opts, neighbours=opts.neighbours.for_bounds(problem.bounds)) if opts.neighbours.trajectories \
            else replace(opts, neighbours=None)
    work = ReplanWork(problem, traj, lock, opts.environment)
    stats: dict[str, Any] = {"split_index": lock if split else None, "lock": lock, "qp_time_s": 0.0}
    try:
        apply_edits(work, cs.edits, split)
        rebuild_corridors(work)
        # a plan that needed time-resolved rows will need them again: try them first
        traj_new, free = search(work, opts, stats, rows_first=bool(traj.stats.get("separation_rows")))
    except Infeasible as exc:
        stats["time_s"] = time.perf_counter() - t_start
        return ReplanResult(
            PlanStatus.INFEASIBLE, None, given, (), str(exc), stats, opts.environment, exc.diagnosis
        )
    new_problem = Problem(work.wps, work.times, work.bounds, work.initial, work.final, traj_new.corridors)
    stats["time_s"] = time.perf_counter() - t_start
    resolved = tuple(sorted(free))
    traj_new = Trajectory(traj_new.times, traj_new.control_points, traj_new.corridors, dict(stats))
    msg = f"re-solved jets {list(resolved)}" if resolved else "no jet needed re-solving"
    return ReplanResult(PlanStatus.OK, traj_new, new_problem, resolved, msg, stats, work.env)


def jets_of(traj: Trajectory) -> FloatArray:
    """All waypoint jets (m, 5, 3) of a trajectory (start jets, then the last end jet)."""
    from planner_core.bezier import hodographs

    d = np.diff(traj.times)
    ctrl = traj.control_points
    out = np.empty((traj.n_segments + 1, JET_ORDER, 3))
    out[:-1, 0] = ctrl[:, 0]
    out[-1, 0] = ctrl[-1, -1]
    for k in range(1, JET_ORDER):
        h = hodographs(ctrl, k, d)
        out[:-1, k] = h[:, 0]
        out[-1, k] = h[-1, -1]
    return out
