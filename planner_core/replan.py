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
"""

from __future__ import annotations

import re
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from planner_core.certificate import certify_rebuilt, end_jet_of, segment_ctrl, start_jet_of
from planner_core.changes import (
    AddObstacles,
    AppendWaypoints,
    ChangeError,
    ChangeSet,
    Edit,
    InsertWaypoint,
    MoveWaypoint,
    RemoveWaypoint,
    SetCorridor,
    SetDuration,
    as_change_set,
    parse_change,
)
from planner_core.localqp import solve_derivatives
from planner_core.problem import JET_ORDER, FloatArray, Polytope, Problem, Trajectory, rest_jet
from planner_core.result import PlanStatus
from planner_core.trajectory import split_at

if TYPE_CHECKING:
    from planner_core.separation import Neighbours

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

TIME_EPS = 1e-9  # a split closer than this to a waypoint time reuses that waypoint
CONTINUITY_TOL = 1e-6  # relative, as verify.py
JOINT_MAX = 6  # free jets solved in one dense QP; longer runs go through the iterative pass


@dataclass(frozen=True)
class Environment:
    """What corridors are built from; needed for obstacle and geometry changes."""

    obstacles: tuple[Polytope, ...] = ()
    map_box: tuple[FloatArray, FloatArray] | None = None
    radius: float = 0.0


@dataclass(frozen=True)
class ReplanOptions:
    max_widen: int = 3
    max_stretch: int = 2
    stretch_factor: float = 1.5
    cost: str = "snap"
    backend: str = "daqp"
    environment: Environment | None = None
    # other vehicles' committed trajectories (planner_core.separation.Neighbours): the re-solved
    # segments get one half-space per near neighbour (planes from the current plan) and are
    # certified against every neighbour near them; default none
    neighbours: Neighbours | None = None


@dataclass(frozen=True)
class ReplanResult:
    status: PlanStatus
    trajectory: Trajectory | None
    problem: Problem  # the updated problem (the input problem when infeasible)
    resolved_jets: tuple[int, ...]
    message: str
    stats: dict[str, Any] = field(default_factory=dict)
    environment: Environment | None = None  # with any added obstacles
    diagnosis: dict[str, Any] | None = None

    @property
    def ok(self) -> bool:
        return self.status is PlanStatus.OK and self.trajectory is not None


class _Infeasible(Exception):
    def __init__(self, message: str, diagnosis: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.diagnosis = diagnosis


# --- splitting ---------------------------------------------------------------


def _split_index(times: FloatArray, t: float) -> tuple[int, bool]:
    """(k, split): k = index the waypoint at t has (or gets); split = a new waypoint is needed."""
    k = int(np.searchsorted(times, t))
    for i in (k - 1, k):
        if 0 <= i < times.size and abs(float(times[i]) - t) <= TIME_EPS:
            return i, False
    return k, True


def split_inside(traj: Trajectory, t: float) -> Trajectory:
    """The same curve with one more segment boundary at t, strictly inside the span.

    The surgery is `planner_core.trajectory.split_at`; this only refuses the cases where
    no new boundary would be made: ValueError when t is not strictly inside the span or
    lies within TIME_EPS of an existing waypoint time.
    """
    t = float(t)
    if not traj.times[0] < t < traj.times[-1]:
        raise ValueError(f"t: {t} is not inside the trajectory span ({traj.t0}, {traj.t_end})")
    k, needed = _split_index(traj.times, t)
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
    k, _ = _split_index(traj.times, float(t))
    s = k - 1
    wps = np.concatenate((problem.waypoints[:k], new_traj.control_points[k, :1], problem.waypoints[k:]))
    corridors = None if problem.corridors is None else (*problem.corridors[: s + 1], *problem.corridors[s:])
    new_problem = Problem(wps, new_traj.times.copy(), problem.bounds, problem.initial, problem.final, corridors)
    return new_problem, new_traj, k


# --- working state -----------------------------------------------------------


def _renumber(d: dict[int, FloatArray], at: int, shift: int) -> dict[int, FloatArray]:
    return {(k + shift if k >= at else k): v for k, v in d.items()}


class _Work:
    """Mutable state of one replan: the edited problem and what to keep from the old trajectory."""

    def __init__(self, problem: Problem, traj: Trajectory, lock: int, env: Environment | None) -> None:
        self.bounds = problem.bounds
        self.wps = problem.waypoints.copy()
        self.times = problem.times.copy()
        self.initial = problem.initial.copy()
        self.final = problem.final.copy()
        # the problem's tuple until an edit writes to it (`writable_corridors`): a move copies no O(m) list
        self.corridors: Sequence[Polytope | None] | None = problem.corridors
        self.old_ctrl = traj.control_points
        self.old_times = traj.times
        self.src = np.arange(traj.n_segments)  # kept segment -> old index; -1: rebuild
        self.touched: set[int] = set()  # segments with src -1 while the layout is unchanged
        self.geo = np.zeros(traj.n_segments, dtype=bool)  # corridor to rebuild from the environment
        self.over: dict[int, FloatArray] = {}  # jets that differ from / are not in the old trajectory
        self.seeds: set[int] = set()
        self.lock = lock
        self.env = env
        self.new_obstacles: tuple[Polytope, ...] = ()
        self.same_layout = True  # segment s still comes from old segment s (no insert/remove/append)

    @property
    def m(self) -> int:
        return int(self.wps.shape[0])

    def free_ok(self, j: int) -> bool:
        return self.lock < j < self.m - 1

    def jet(self, i: int) -> FloatArray:
        if i in self.over:
            return self.over[i]
        if i < self.m - 1 and self.src[i] >= 0:
            o = int(self.src[i])
            return start_jet_of(self.old_ctrl[o], self._old_duration(o))
        if i > 0 and self.src[i - 1] >= 0:
            o = int(self.src[i - 1])
            return end_jet_of(self.old_ctrl[o], self._old_duration(o))
        raise AssertionError(f"jet {i} is neither kept nor overridden")

    def _old_duration(self, o: int) -> float:
        return float(self.old_times[o + 1] - self.old_times[o])

    def touch(self, s: int) -> None:
        """Segment s will be rebuilt: remember its end jets first."""
        for i in (s, s + 1):
            if i not in self.over:
                self.over[i] = self.jet(i)
        self.src[s] = -1
        self.touched.add(s)

    def writable_corridors(self) -> list[Polytope | None]:
        if self.corridors is None:
            self.corridors = [None] * (self.m - 1)
        elif not isinstance(self.corridors, list):
            self.corridors = list(self.corridors)
        return self.corridors

    def corridor_tuple(self) -> tuple[Polytope | None, ...] | None:
        return None if self.corridors is None else tuple(self.corridors)  # no copy while still a tuple

    def rebuilt(self) -> list[int]:
        """Segments marked for rebuilding, in order (O(change) while the layout is unchanged)."""
        if self.same_layout:
            return sorted(self.touched)
        return [int(s) for s in np.flatnonzero(self.src < 0)]

    def seed(self, *jets: int) -> None:
        self.seeds.update(j for j in jets if self.free_ok(j))

    def check_index(self, i: int, lo: int, hi: int, what: str) -> None:
        if not lo <= i <= hi:
            raise ChangeError(what, f"index {i} out of range {lo}..{hi}")

    # --- edits ---

    def move(self, j: int, pos: FloatArray) -> None:
        m = self.m
        self.check_index(j, 0, m - 1, "move.index")
        if j <= self.lock and not (j == 0 and self.lock == 0):
            raise ChangeError("move.index", f"waypoint {j} is at or before from_time (split waypoint {self.lock})")
        for s in (j - 1, j):
            if 0 <= s < m - 1:
                self.touch(s)
                self.geo[s] = True
        self.wps[j] = pos
        jet = self.over[j].copy()
        jet[0] = pos
        self.over[j] = jet
        if j == 0:
            self.initial = jet
        if j == m - 1:
            self.final = jet
        self.seed(j - 1 if j == m - 1 else j, 1 if j == 0 else j)

    def set_duration(self, s: int, d: float) -> None:
        self.check_index(s, 0, self.m - 2, "duration.segment")
        if s < self.lock:
            raise ChangeError("duration.segment", f"segment {s} is before from_time")
        self.touch(s)
        self.times[s + 1 :] += d - float(self.times[s + 1] - self.times[s])
        self.seed(s, s + 1)

    def set_corridor(self, s: int, poly: Polytope | None) -> None:
        self.writable_corridors()[s] = poly
        if poly is None or self.src[s] < 0:
            return
        v = poly.violation(self.old_ctrl[int(self.src[s])])
        if v > 1e-9:
            if s < self.lock:
                raise _Infeasible(
                    f"segment {s}, before from_time (being flown), leaves its new corridor by {v:.3g}: "
                    "it cannot be replanned; brake",
                    {"kind": "corridor", "segment": s, "waypoint": None, "before_from_time": True},
                )
            self.touch(s)
            self.seed(s, s + 1)

    def insert(self, i: int, pos: FloatArray, t: float | None) -> None:
        self.check_index(i, 1, self.m - 1, "insert.index")
        if i <= self.lock:
            raise ChangeError("insert.index", f"waypoint {i} would be at or before from_time")
        s = i - 1
        t0, t1 = float(self.times[s]), float(self.times[s + 1])
        if t is None:
            a = float(np.linalg.norm(pos - self.wps[s]))
            b = float(np.linalg.norm(self.wps[s + 1] - pos))
            t = t0 + (t1 - t0) * (0.5 if a + b == 0.0 else a / (a + b))
        if not t0 < t < t1:
            raise ChangeError("insert.time", f"{t} must lie strictly between {t0} and {t1}")
        self.touch(s)
        self.same_layout = False
        self.over = _renumber(self.over, i, 1)
        self.over[i] = rest_jet(pos)
        self.seeds = {j + 1 if j >= i else j for j in self.seeds}
        self.wps = np.insert(self.wps, i, pos, axis=0)
        self.times = np.insert(self.times, i, t)
        self.src = np.insert(self.src, i, -1)
        self.geo = np.insert(self.geo, i, True)
        self.geo[s] = True
        if self.corridors is not None:
            corr = self.writable_corridors()
            corr.insert(i, corr[s])
        self.seed(i)

    def remove(self, i: int, corridor: Polytope | None) -> None:
        self.check_index(i, 1, self.m - 2, "remove.index")
        if i <= self.lock:
            raise ChangeError("remove.index", f"waypoint {i} is at or before from_time")
        self.touch(i - 1)
        self.touch(i)
        self.same_layout = False
        del self.over[i]
        self.over = _renumber(self.over, i + 1, -1)
        self.seeds = {j - 1 if j > i else j for j in self.seeds if j != i}
        self.wps = np.delete(self.wps, i, axis=0)
        self.times = np.delete(self.times, i)
        self.src = np.delete(self.src, i)
        self.geo = np.delete(self.geo, i)
        if self.corridors is not None:
            corr = self.writable_corridors()
            del corr[i]
            if corridor is not None:
                corr[i - 1] = corridor
            elif self.env is not None:
                self.geo[i - 1] = True
            else:
                raise ChangeError(
                    "remove.corridor",
                    "the problem has corridors: give the merged segment's corridor or the scenario's obstacles",
                )
        self.seed(i - 1, i)

    def append(self, edit: AppendWaypoints) -> None:
        m_old = self.m
        self.same_layout = False
        k = edit.positions.shape[0]
        last = m_old - 1
        self.over.setdefault(last, self.jet(last))
        durations = edit.durations if edit.durations is not None else _allocate(self.wps[last], edit.positions, self)
        new_times = float(self.times[-1]) + np.cumsum(durations)
        final = rest_jet(edit.positions[-1]) if edit.final is None else np.asarray(edit.final, dtype=float)
        for n in range(k - 1):
            self.over[m_old + n] = rest_jet(edit.positions[n])
        self.over[m_old + k - 1] = final
        self.final = final
        self.wps = np.vstack([self.wps, edit.positions])
        self.times = np.concatenate([self.times, new_times])
        self.src = np.concatenate([self.src, np.full(k, -1)])
        self.geo = np.concatenate([self.geo, np.full(k, edit.corridors is None)])
        if edit.corridors is not None:
            if self.corridors is None:
                self.corridors = [None] * (m_old - 1)
            self.writable_corridors().extend(edit.corridors)
        elif self.corridors is not None:
            if self.env is None:
                raise ChangeError(
                    "append.corridors",
                    "the problem has corridors: give one per new segment or the scenario's obstacles",
                )
            self.writable_corridors().extend([None] * k)
        self.seed(*range(last, self.m - 1))

    def add_obstacles(self, obstacles: tuple[Polytope, ...]) -> None:
        if self.env is None:
            raise ChangeError("obstacles", "obstacle changes need the scenario's environment (map, radius, obstacles)")
        self.new_obstacles = self.new_obstacles + obstacles

    def stretch(self, factor: float) -> bool:
        """Lengthen the segments next to the seeds; False when none can change."""
        segs = sorted({s for j in self.seeds for s in (j - 1, j) if self.lock <= s < self.m - 1})
        for s in segs:
            self.set_duration(s, float(self.times[s + 1] - self.times[s]) * factor)
        return bool(segs)


def _allocate(start: FloatArray, positions: FloatArray, work: _Work) -> FloatArray:
    pts = np.vstack([start, positions])
    try:
        from planner_core.timing import allocate_times

        times = allocate_times(pts, work.bounds, t0=0.0)
        return np.asarray(np.diff(times), dtype=float)
    except ImportError:
        lo, hi = work.bounds.axis_limits()
        vmax = float(np.min(np.minimum(-lo[0], hi[0])))
        dist = np.linalg.norm(np.diff(pts, axis=0), axis=1)
        return np.asarray(np.maximum(2.0 * dist / max(vmax, 1e-3), 1.0), dtype=float)


# --- corridors from the environment -----------------------------------------


def _corridor_error(exc: Exception, offset: int = 0) -> _Infeasible:
    seg = getattr(exc, "segment", None)
    wp = getattr(exc, "waypoint", None)
    diag = {
        "kind": "corridor",
        "segment": None if seg is None else seg + offset,
        "waypoint": None if wp is None else wp + offset,
        "obstacle": getattr(exc, "obstacle", None),
    }
    text = str(exc)
    if offset:  # built on a two-waypoint sub-list: renumber the message's local indices
        text = re.sub(r"(segment|waypoint|->) (\d+)", lambda mt: f"{mt.group(1)} {int(mt.group(2)) + offset}", text)
    return _Infeasible(f"corridor: {text}", diag)


def _rebuild_corridors(work: _Work) -> None:
    env = work.env
    if env is None or (work.corridors is None and not work.new_obstacles):
        return
    from planner_core.geometry import CorridorError, build_corridors, update_corridors

    corridors = work.writable_corridors() if work.corridors is None else work.corridors
    obstacles = (*env.obstacles, *work.new_obstacles)
    missing = np.zeros(work.m - 1, dtype=bool)
    # identity scan first (`None in` would call Polytope.__eq__ per entry); indices only when needed
    if [c for c in corridors if c is None]:
        missing[[i for i, c in enumerate(corridors) if c is None]] = True
        missing[: max(work.lock - 1, 0)] = False  # the past keeps whatever it had
    for s in (int(i) for i in np.flatnonzero(work.geo | missing)):
        old = corridors[s]  # entries before s are the only ones written so far
        if not work.new_obstacles and old is not None and float((work.wps[s : s + 2] @ old.A.T - old.b).max()) < 0.0:
            # the old corridor holds the new straight segment: keeping it is safe (the QP keeps
            # the curve inside) and skips a corridor build, the slow part of a geometric change.
            # With new obstacles a fresh build is roomier than the old corridor cut by a new plane.
            continue
        try:
            work.writable_corridors()[s] = build_corridors(work.wps[s : s + 2], obstacles, env.map_box, env.radius)[0]
        except CorridorError as exc:
            raise _corridor_error(exc, s) from exc
    if work.new_obstacles:
        # segments before the one being flown (the one ending at the split) are the past
        first = max(work.lock - 1, 0)
        try:
            current = tuple(c for c in work.writable_corridors()[first:] if c is not None)
            # prune=False: same region and certificates, without a vertex enumeration per
            # affected corridor (that was most of a pop-up replan's time)
            updated, changed = update_corridors(
                work.wps[first:], current, env.obstacles, work.new_obstacles, env.map_box, env.radius,
                prune=False,
            )
        except CorridorError as exc:
            err = _corridor_error(exc, first)
            if err.diagnosis is not None and err.diagnosis.get("segment") is not None and err.diagnosis["segment"] < work.lock:
                raise _Infeasible(f"{err} — the piece being flown is blocked: brake", err.diagnosis) from exc
            raise err from exc
        for s in changed:
            work.set_corridor(int(s) + first, updated[int(s)])
    work.env = Environment(obstacles, env.map_box, env.radius)


# --- solving -----------------------------------------------------------------


def _segments_of(free: set[int], m: int) -> set[int]:
    return {s for j in free for s in (j - 1, j) if 0 <= s < m - 1}


def _widen(free: set[int], work: _Work) -> set[int]:
    if not free:
        base = {j for s in work.rebuilt() for j in (s, s + 1)}
        return {j for j in base if work.free_ok(j)}
    return free | {n for j in free for n in (j - 1, j + 1) if work.free_ok(n)}


def _solve(work: _Work, free: set[int], opts: ReplanOptions) -> tuple[dict[int, FloatArray], float]:
    """Jets for `free`: one QP over the segments they touch (O(len(free)), never O(m))."""
    if not free:
        return {}, 0.0
    segs = _segments_of(free, work.m)
    jets = {i: work.jet(i) for s in segs for i in (s, s + 1)}
    durations = {s: float(work.times[s + 1] - work.times[s]) for s in segs}
    corridors = work.corridors
    cut = _neighbour_cut(work, sorted(segs), opts)

    def corridor_of(s: int) -> Polytope | None:
        if s in cut:
            return cut[s]
        return None if corridors is None else corridors[s]

    if len(free) > JOINT_MAX and max(free) - min(free) + 1 == len(free):
        # a long run of free jets (a big append): the iterative pass, O(run), not one dense QP
        return _solve_iterative(work, free, opts, cut)
    if opts.cost != "snap":  # other costs: the core's general jet solver on a window sub-problem
        return _solve_general(work, free, opts, cut)
    t0 = time.perf_counter()
    sol = solve_derivatives(jets, durations, work.bounds, corridor_of, sorted(free), backend=opts.backend)
    if not sol.ok:
        raise _Infeasible(sol.message)
    return sol.jets, time.perf_counter() - t0


def _neighbour_cut(work: _Work, segs: list[int], opts: ReplanOptions) -> dict[int, Polytope | None]:
    """The corridors of the re-solved segments cut by their neighbour faces (empty: no neighbours)."""
    nb = opts.neighbours
    if nb is None or not segs:
        return {}
    from planner_core.separation import NoFace, add_faces, neighbour_faces, reference_points

    old = Trajectory(work.old_times, work.old_ctrl)
    straight = np.stack([work.wps[segs], work.wps[[s + 1 for s in segs]]], axis=1)  # (k, 2, 3)
    u = np.linspace(0.0, 1.0, 10)[None, :, None]
    lines = straight[:, :1] * (1.0 - u) + straight[:, 1:] * u  # (k, 10, 3)
    full = np.zeros((work.m - 1, 10, 3))
    full[segs] = lines
    ref = reference_points(work.times, full, old, segs)
    try:
        faces = neighbour_faces(work.times, ref, nb, segs, give_up=True)
    except NoFace as exc:
        raise _Infeasible(f"separation: {exc}") from exc
    corridors = work.corridors
    return {s: add_faces(None if corridors is None else corridors[s], faces[s]) for s in faces}


def _solve_rows(work: _Work, free: set[int], opts: ReplanOptions) -> tuple[dict[int, FloatArray], float]:
    """Jets for `free` with time-resolved separation rows (`separation.planning_rows`, planes per
    common piece of the current plan and each near neighbour) in the general jet solver: for a
    neighbour that crosses our path within one segment, at another time."""
    from planner_core.jets import ProblemCache, solve_jets
    from planner_core.separation import planning_rows, reference_trajectory

    nb = opts.neighbours
    if nb is None or not free:
        return {}, 0.0
    lo = min(free) - 1
    sub, jets = _sub_problem(work, lo, max(free) + 1)
    old = Trajectory(work.old_times, work.old_ctrl)
    covers = old.t0 <= sub.times[0] + TIME_EPS and old.t_end >= sub.times[-1] - TIME_EPS
    rows = planning_rows(sub.times, old if covers else reference_trajectory(sub, None), nb)
    t0 = time.perf_counter()
    res = solve_jets(sub, jets, [j - lo for j in sorted(free)], cost=opts.cost if opts.cost in ("snap", "jerk") else "snap",
                     backend=opts.backend, cache=ProblemCache(sub, extra_rows=rows))
    elapsed = time.perf_counter() - t0
    if not res.ok:
        raise _Infeasible(f"QP {res.status.value} for jets {sorted(free)} with {rows.rhs.size} separation rows")
    return {j: res.jets[j - lo] for j in free}, elapsed


def _sub_problem(work: _Work, lo: int, hi: int,
                 cut: dict[int, Polytope | None] | None = None) -> tuple[Problem, FloatArray]:
    """Waypoints lo..hi as a problem of their own, the end jets fixed to the current ones."""
    jets = np.stack([work.jet(i) for i in range(lo, hi + 1)])
    corr = None if work.corridors is None else tuple(work.corridors[lo:hi])
    if cut:
        base = corr if corr is not None else (None,) * (hi - lo)
        corr = tuple(cut.get(s, c) for s, c in zip(range(lo, hi), base, strict=True))
    return Problem(work.wps[lo : hi + 1], work.times[lo : hi + 1], work.bounds, jets[0], jets[-1], corr), jets


def _solve_iterative(work: _Work, free: set[int], opts: ReplanOptions,
                     cut: dict[int, Polytope | None] | None = None) -> tuple[dict[int, FloatArray], float]:
    from planner_core.iterative import IterativeOptions, plan_iterative

    lo, hi = min(free) - 1, max(free) + 1
    sub, _ = _sub_problem(work, lo, hi, cut)
    t0 = time.perf_counter()
    # no stretching inside: replan's own stretch step keeps the later segments' times consistent
    res = plan_iterative(sub, IterativeOptions(cost=opts.cost, backend=opts.backend, max_stretches=0, diagnose=False))
    elapsed = time.perf_counter() - t0
    if not res.ok or res.trajectory is None or not np.array_equal(res.trajectory.times, sub.times):
        raise _Infeasible(f"iterative pass over jets {min(free)}..{max(free)}: {res.message}")
    ctrl = res.trajectory.control_points
    d = np.diff(sub.times)
    return {j: start_jet_of(ctrl[j - lo], float(d[j - lo])) for j in free}, elapsed


def _solve_general(work: _Work, free: set[int], opts: ReplanOptions,
                   cut: dict[int, Polytope | None] | None = None) -> tuple[dict[int, FloatArray], float]:
    from planner_core.jets import solve_jets

    lo = min(free) - 1
    sub, jets = _sub_problem(work, lo, max(free) + 1, cut)
    t0 = time.perf_counter()
    res = solve_jets(sub, jets, [j - lo for j in sorted(free)], cost=opts.cost, backend=opts.backend)
    elapsed = time.perf_counter() - t0
    if not res.ok:
        raise _Infeasible(f"QP {res.status.value} for jets {sorted(free)}")
    return {j: res.jets[j - lo] for j in free}, elapsed


def _assemble(work: _Work, solved: dict[int, FloatArray], free: set[int]) -> tuple[Trajectory, list[int]]:
    m = work.m
    rebuild = sorted(set(work.rebuilt()) | _segments_of(free, m))
    times = work.times
    if work.same_layout:  # a plain copy (memcpy) is much cheaper than a gather at large m
        ctrl = work.old_ctrl.copy()
    else:
        ctrl = np.empty((m - 1, 10, 3))
        keep = np.ones(m - 1, dtype=bool)
        keep[rebuild] = False
        ctrl[keep] = work.old_ctrl[work.src[keep]]
    for s in rebuild:
        j0 = solved[s] if s in solved else work.jet(s)
        j1 = solved[s + 1] if s + 1 in solved else work.jet(s + 1)
        ctrl[s] = segment_ctrl(j0, j1, float(times[s + 1] - times[s]))
    return Trajectory(times.copy(), ctrl, work.corridor_tuple()), rebuild


def _certify(traj: Trajectory, work: _Work, rebuild: list[int]) -> str | None:
    """Hull certificate of the rebuilt segments and C^4 continuity with their neighbours."""
    return certify_rebuilt(
        traj.control_points, traj.times, rebuild, work.bounds, traj.corridors, work.initial, work.final,
        continuity_tol=CONTINUITY_TOL,
    )


def _apply(work: _Work, edits: Sequence[Edit], split: bool) -> None:
    """Apply edits (indices of the problem as given; shifted past a split waypoint)."""

    def wp(i: int) -> int:
        return i + 1 if split and i >= work.lock else i

    def seg(s: int) -> int:
        return s + 1 if split and s >= work.lock - 1 else s

    ordered = sorted(
        edits,
        key=lambda e: [MoveWaypoint, SetDuration, SetCorridor, RemoveWaypoint, InsertWaypoint, AppendWaypoints, AddObstacles].index(type(e)),
    )
    for e in ordered:
        if isinstance(e, MoveWaypoint):
            work.move(wp(e.index), np.asarray(e.position, dtype=float))
        elif isinstance(e, SetDuration):
            s = seg(e.segment)
            d = e.duration
            if split and e.segment == work.lock - 1:  # the split segment: keep the flown piece
                d -= float(work.times[s] - work.times[s - 1])
                if d <= 0.0:
                    raise ChangeError("duration.duration", "shorter than the part already flown before from_time")
            work.set_duration(s, d)
        elif isinstance(e, SetCorridor):
            if not 0 <= e.segment < work.m - 1 - (1 if split else 0):
                raise ChangeError("corridor.segment", f"segment {e.segment} out of range")
            s = seg(e.segment)
            if s < work.lock:
                raise ChangeError("corridor.segment", f"segment {e.segment} is before from_time")
            work.set_corridor(s, e.corridor)
        elif isinstance(e, RemoveWaypoint):
            work.remove(wp(e.index), e.corridor)
        elif isinstance(e, InsertWaypoint):
            work.insert(wp(e.index), np.asarray(e.position, dtype=float), e.time)
        elif isinstance(e, AppendWaypoints):
            work.append(e)
        elif isinstance(e, AddObstacles):
            work.add_obstacles(e.obstacles)


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
            lock, split = _split_index(problem.times, t)
            if split:
                problem, traj, lock = split_problem_at(problem, traj, t)
    if opts.neighbours is not None:
        from dataclasses import replace

        opts = replace(opts, neighbours=opts.neighbours.for_bounds(problem.bounds)) if opts.neighbours.trajectories \
            else replace(opts, neighbours=None)
    work = _Work(problem, traj, lock, opts.environment)
    stats: dict[str, Any] = {"split_index": lock if split else None, "lock": lock, "qp_time_s": 0.0}
    try:
        _apply(work, cs.edits, split)
        _rebuild_corridors(work)
        # a plan that needed time-resolved rows will need them again: try them first
        traj_new, free = _search(work, opts, stats, rows_first=bool(traj.stats.get("separation_rows")))
    except _Infeasible as exc:
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


def _search(work: _Work, opts: ReplanOptions, stats: dict[str, Any],
            rows_first: bool = False) -> tuple[Trajectory, set[int]]:
    """Seeds first; widen one neighbour per step; then stretch the touched durations."""
    attempts = 0
    last = ""
    checked = False
    for stretch in range(opts.max_stretch + 1):
        if stretch:
            if not work.stretch(opts.stretch_factor):
                break
            stats["stretched"] = stretch
        free = set(work.seeds)
        for widen in range(opts.max_widen + 1):
            attempts += 1
            order = ((True, False) if rows_first else (False, True)) if opts.neighbours is not None else (False,)
            for rows in order:
                # with neighbours: one face per segment first, then time-resolved rows
                try:
                    solved, qp_time = _solve_rows(work, free, opts) if rows else _solve(work, free, opts)
                    stats["qp_time_s"] += qp_time
                    traj, rebuild = _assemble(work, solved, free)
                    failure = _certify(traj, work, rebuild)
                    if failure is None and opts.neighbours is not None and rebuild:
                        failure = _certify_separation(traj, rebuild, opts.neighbours, stats)
                    if failure is None:
                        stats.update(attempts=attempts, widened=widen, rebuilt_segments=rebuild)
                        if rows:
                            stats["separation_rows"] = True
                        return traj, free
                    last = f"certificate failed: {failure}"
                except _Infeasible as exc:
                    last = str(exc)
            if not checked:
                # A waypoint outside its corridor fails every attempt (the certificate checks
                # P^0 and P^9): name it now instead of widening and stretching in vain. Checked
                # only after a failure, off the success path; nothing has stretched yet, so the
                # touched segments are the edit's own.
                _check_waypoints_in_corridors(work)
                checked = True
            wider = _widen(free, work)
            if wider == free:
                break
            free = wider
    raise _Infeasible(
        f"no feasible local replan after {attempts} attempts (widening up to {opts.max_widen}, "
        f"stretching up to {opts.max_stretch}x): {last}",
        {"kind": "replan", "seeds": sorted(work.seeds), "attempts": attempts},
    )


def _certify_separation(traj: Trajectory, rebuild: list[int], nb: Neighbours, stats: dict[str, Any]) -> str | None:
    """The rebuilt span of `traj` certified against every neighbour near it (kept segments were
    certified when they were planned); the certificates go to stats["separation"]."""
    from planner_core.separation import certify_all

    t0 = time.perf_counter()
    end = max(rebuild) + 1
    # the span reaches for ever when the rebuilt part is the end: the held last point stays reserved
    t_to = None if end >= traj.n_segments else float(traj.times[end])
    certs, failure, near = certify_all(traj, nb, float(traj.times[min(rebuild)]), t_to)
    stats["separation"] = {"ok": failure is None, "near": near, "neighbours": len(nb.trajectories),
                           "certificates": certs, "time_certify": time.perf_counter() - t0}
    return None if failure is None else f"separation: {failure.message}"


def _check_waypoints_in_corridors(work: _Work) -> None:
    if work.corridors is None:
        return
    for s in work.rebuilt():
        poly = work.corridors[s]
        if poly is None or poly.A.shape[0] == 0:
            continue
        over = (work.wps[s : s + 2] @ poly.A.T - poly.b).max(axis=1)  # both ends at once
        for i, v in zip((s, s + 1), over.tolist(), strict=True):
            if v > 1e-9:
                raise _Infeasible(
                    f"waypoint {i} at {work.wps[i].tolist()} is outside the corridor of segment {s} (by {v:.3g})",
                    {"kind": "corridor", "segment": s, "waypoint": i},
                )


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
