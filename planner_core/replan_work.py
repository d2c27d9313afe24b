"""The state of one local replan (`planner_core.replan`): its options and result
(`Environment`, `ReplanOptions`, `ReplanResult`), the working copy of the problem and what is kept
from the current trajectory (`ReplanWork`, with one method per edit), `apply_edits` (a change's
edits in their order, past a split waypoint) and `rebuild_corridors` (from the environment).
`Infeasible` carries a failure to `replan`, which returns it as a result.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from planner_core.certificate import end_jet_of, start_jet_of
from planner_core.changes import (
    AddObstacles,
    AppendWaypoints,
    ChangeError,
    Edit,
    InsertWaypoint,
    MoveWaypoint,
    RemoveWaypoint,
    SetCorridor,
    SetDuration,
)
from planner_core.problem import FloatArray, Polytope, Problem, Trajectory, rest_jet
from planner_core.result import PlanStatus

if TYPE_CHECKING:
    from planner_core.separation import Neighbours

TIME_EPS = 1e-9  # a split closer than this to a waypoint time reuses that waypoint


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


class Infeasible(Exception):
    def __init__(self, message: str, diagnosis: dict[str, Any] | None = None) -> None:
        super().__init__(message)
        self.diagnosis = diagnosis


# --- splitting ---------------------------------------------------------------


def split_index(times: FloatArray, t: float) -> tuple[int, bool]:
    """(k, split): k = index the waypoint at t has (or gets); split = a new waypoint is needed."""
    k = int(np.searchsorted(times, t))
    for i in (k - 1, k):
        if 0 <= i < times.size and abs(float(times[i]) - t) <= TIME_EPS:
            return i, False
    return k, True


# --- working state -----------------------------------------------------------


def _renumber(d: dict[int, FloatArray], at: int, shift: int) -> dict[int, FloatArray]:
    return {(k + shift if k >= at else k): v for k, v in d.items()}


class ReplanWork:
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
                raise Infeasible(
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


def _allocate(start: FloatArray, positions: FloatArray, work: ReplanWork) -> FloatArray:
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


def _corridor_error(exc: Exception, offset: int = 0) -> Infeasible:
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
    return Infeasible(f"corridor: {text}", diag)


def rebuild_corridors(work: ReplanWork) -> None:
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
                raise Infeasible(f"{err} — the piece being flown is blocked: brake", err.diagnosis) from exc
            raise err from exc
        for s in changed:
            work.set_corridor(int(s) + first, updated[int(s)])
    work.env = Environment(obstacles, env.map_box, env.radius)


# --- a change's edits ----------------------------------------------------------


def apply_edits(work: ReplanWork, edits: Sequence[Edit], split: bool) -> None:
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
