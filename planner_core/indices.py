"""The user's waypoint indices and the planned ones, when a plan has knots.

The fastest allocation may split a long leg with knots (`planner_core.missions`), and a
replan from a `from_time` adds a split waypoint: the planned problem then has more
waypoints than the user gave. A `WaypointMap` says where each user waypoint sits
(`index[i]`, strictly increasing, first 0, last the planned count - 1); every other planned
waypoint is a knot on the user segment it lies in. A change the user writes counts user
waypoints and user segments; `to_planned` turns it into the planned problem's indices and
`PlannedChange.map_after` gives the map of the replanned trajectory. Rules on a user
segment that holds knots (its "pieces"):

- move waypoint i: the knots of the user segments next to it keep their place along the
  segment (the same fraction of the way), so the segment stays straight;
- duration of segment s: the segment's total. Without `from_time` every piece scales by
  new / old; with it the pieces flown and the one being flown keep their durations and the
  rest is spread over the pieces after it in proportion (the piece being flown takes the
  change only when it is the segment's last);
- corridor of segment s: every piece not yet flown gets it;
- insert waypoint i (into segment i - 1): at the time given, else at the user segment's
  time split by distance (as replan splits one segment); it goes between the knots around that time, and the knots are
  moved onto the two new legs at their fraction of the time before / after it, so each
  piece keeps its duration and its average speed;
- remove waypoint i: the two segments merge and their knots are moved onto the merged
  straight leg at their fraction of its time (a given corridor goes to every piece).
Knots at or before `from_time`, and the one ending the piece being flown, are never moved.
Messages and diagnoses of the replan are relabelled into user indices (`relabel_text`,
`relabel_diagnosis`), a knot named as "a knot on segment s".
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from planner_core.changes import (
    AppendWaypoints,
    ChangeError,
    ChangeSet,
    Edit,
    InsertWaypoint,
    MoveWaypoint,
    RemoveWaypoint,
    SetCorridor,
    SetDuration,
)
from planner_core.errors import FieldError
from planner_core.problem import FloatArray

IntArray = NDArray[np.int64]
TIME_EPS = 1e-9  # as planner_core.replan.TIME_EPS: a from_time this close to a waypoint time is that waypoint

__all__ = ["PlannedChange", "WaypointMap", "to_planned"]


@dataclass(frozen=True)
class WaypointMap:
    index: IntArray  # (n,) planned index of each user waypoint
    planned: int  # planned waypoints (user waypoints plus knots)

    @classmethod
    def identity(cls, m: int) -> WaypointMap:
        return cls(np.arange(m, dtype=np.int64), m)

    @classmethod
    def checked(cls, index: ArrayLike, planned: int, field: str = "waypoint_index") -> WaypointMap:
        """The map, or FieldError when it cannot describe `planned` waypoints."""
        idx = np.asarray(index)
        if idx.ndim != 1 or idx.size < 2 or not np.issubdtype(idx.dtype, np.integer):
            raise FieldError(field, f"expected a list of >= 2 integer indices, got {np.asarray(index).tolist()!r}")
        idx = idx.astype(np.int64)
        if idx[0] != 0 or idx[-1] != planned - 1:
            raise FieldError(field, f"must start at 0 and end at {planned - 1} (the last of {planned} planned "
                                    f"waypoints), got {int(idx[0])} .. {int(idx[-1])}")
        bad = np.flatnonzero(np.diff(idx) < 1)
        if bad.size:
            raise FieldError(f"{field}[{int(bad[0]) + 1}]", "indices must be strictly increasing")
        return cls(idx, planned)

    @property
    def n(self) -> int:
        return int(self.index.size)

    @property
    def is_identity(self) -> bool:
        return self.n == self.planned

    def segment_of(self, s: int) -> int:
        """The user segment planned segment s lies on."""
        return int(np.searchsorted(self.index, s, side="right")) - 1

    def user_of(self, j: int) -> int | None:
        """The user index of planned waypoint j; None for a knot."""
        u = int(np.searchsorted(self.index, j))
        return u if u < self.n and int(self.index[u]) == j else None

    def pieces(self, s: int) -> range:
        """The planned segments of user segment s."""
        return range(int(self.index[s]), int(self.index[s + 1]))

    def split_at(self, k: int | None) -> WaypointMap:
        """After replan inserted a split waypoint (a knot to the user) at planned index k."""
        if k is None:
            return self
        return WaypointMap(self.index + (self.index >= k), self.planned + 1)

    def waypoint_label(self, j: int) -> str:
        u = self.user_of(j)
        return f"waypoint {u}" if u is not None else f"a knot on segment {self.segment_of(j)}"

    def relabel_text(self, text: str) -> str:
        """A replan message with planned indices, in user indices."""
        if self.is_identity:
            return text

        def jets(found: Sequence[int]) -> str:
            users = [u for u in (self.user_of(j) for j in found) if u is not None]
            knots = len(found) - len(users)
            return f"waypoints {users}" + (f" and {knots} knot(s)" if knots else "")

        text = re.sub(r"\bjets \[([\d, ]*)\]",
                      lambda mt: jets([int(x) for x in mt.group(1).split(",") if x.strip()]), text)
        text = re.sub(r"\bjets (\d+)\.\.(\d+)",
                      lambda mt: jets(list(range(int(mt.group(1)), int(mt.group(2)) + 1))), text)
        text = re.sub(r"\bwaypoint (\d+)", lambda mt: self.waypoint_label(int(mt.group(1))), text)
        return re.sub(r"\bsegment (\d+)", lambda mt: f"segment {self.segment_of(int(mt.group(1)))}", text)

    def relabel_diagnosis(self, diagnosis: dict[str, Any]) -> dict[str, Any]:
        out = dict(diagnosis)
        if isinstance(out.get("segment"), int):
            out["segment"] = self.segment_of(out["segment"])
        if isinstance(out.get("waypoint"), int):
            j = out["waypoint"]
            out["waypoint"] = self.user_of(j)
            if out["waypoint"] is None:
                out["knot_on_segment"] = self.segment_of(j)
        if isinstance(out.get("seeds"), list):
            out["seeds"] = [u for u in (self.user_of(j) for j in out["seeds"]) if u is not None]
        return out


@dataclass(frozen=True)
class PlannedChange:
    """A user's change in planned indices, and what it does to the map."""

    change: ChangeSet
    before: WaypointMap
    structural: tuple[str, int, int] | None  # ("insert" | "remove", user index, planned index as given)
    appended: int  # user waypoints appended at the end

    def map_after(self, split_index: int | None, planned: int) -> WaypointMap:
        """The map of the replanned trajectory (`split_index`: replan's stats; `planned`: its waypoints)."""
        wm = self.before.split_at(split_index)
        idx = wm.index
        if self.structural is not None:
            kind, u, p = self.structural
            if split_index is not None and p >= split_index:  # replan shifts indices past its split
                p += 1
            if kind == "insert":
                idx = np.concatenate([idx[:u], [p], idx[u:] + 1])
            else:
                idx = np.concatenate([idx[:u], idx[u + 1:] - 1])
        if self.appended:
            idx = np.concatenate([idx, planned - self.appended + np.arange(self.appended)])
        return WaypointMap.checked(idx.astype(np.int64), planned)


def _locked(times: FloatArray, from_time: float | None) -> tuple[int, bool]:
    """(the last planned waypoint at or before from_time, -1: none; whether from_time falls inside
    a piece), as replan locks them."""
    if from_time is None or from_time <= float(times[0]) + TIME_EPS:
        return -1, False
    if from_time >= float(times[-1]) - TIME_EPS:
        return int(times.size) - 1, False
    k = int(np.searchsorted(times, from_time))
    for i in (k - 1, k):
        if 0 <= i < times.size and abs(float(times[i]) - from_time) <= TIME_EPS:
            return i, False
    return k - 1, True


def _out_of_range(field: str, what: str, i: int, lo: int, hi: int, n: int) -> ChangeError:
    return ChangeError(field, f"{what} {i} out of range {lo}..{hi} (the mission has {n} waypoints)")


def to_planned(
    change: ChangeSet, wmap: WaypointMap, waypoints: FloatArray, times: FloatArray
) -> PlannedChange:
    """`change` (user indices) in the indices of the planned problem (`waypoints`, `times`:
    planned, before the change); raises ChangeError naming the user index."""
    if waypoints.shape[0] != wmap.planned or times.shape[0] != wmap.planned:
        raise ChangeError("waypoint_index", f"describes {wmap.planned} planned waypoints, the trajectory has "
                                            f"{waypoints.shape[0]}")
    n, idx = wmap.n, wmap.index
    last, inside = _locked(times, change.from_time)
    # knots never move at or before from_time, nor the one ending the piece being flown (its
    # start jet is pinned: moving its end is what a local replan can least often do)
    frozen = last + 1 if inside else last
    t_from = change.from_time
    moved: dict[int, FloatArray] = {}  # user waypoint -> new position
    edits: list[Edit] = []
    knot_to: dict[int, FloatArray] = {}  # planned knot -> new position
    structural: tuple[str, int, int] | None = None
    appended = 0

    def spread(seg: int, d: float) -> list[SetDuration]:
        """User segment seg's new total d over its pieces (module docstring)."""
        pieces = list(wmap.pieces(seg))
        dur = {p: float(times[p + 1] - times[p]) for p in pieces}
        past = [p for p in pieces if t_from is not None and float(times[p + 1]) <= t_from + TIME_EPS]
        future = [p for p in pieces if t_from is None or float(times[p]) >= t_from - TIME_EPS]
        current = [p for p in pieces if p not in past and p not in future]  # being flown at from_time
        if not future and not current:
            raise ChangeError("duration.segment", f"segment {seg} is before from_time")
        kept = sum(dur[p] for p in past)
        if not future:  # only the piece being flown is left: it takes the change (replan keeps its flown part)
            assert t_from is not None
            flown = kept + t_from - float(times[current[0]])
            if d <= flown:
                raise ChangeError("duration.duration", f"segment {seg}: {d:g} s is not longer than the "
                                                       f"{flown:g} s flown before from_time")
            return [SetDuration(current[0], d - kept)]
        # the piece being flown keeps its duration: changing it against its pinned start jet is
        # what a local replan can least often do
        kept += sum(dur[p] for p in current)
        if d <= kept:
            raise ChangeError("duration.duration", f"segment {seg}: {d:g} s is not longer than the {kept:g} s "
                                                   "flown or being flown at from_time")
        scale = (d - kept) / sum(dur[p] for p in future)
        return [SetDuration(p, dur[p] * scale) for p in future]

    def check_segment(s: int, field: str) -> None:
        if not 0 <= s <= n - 2:
            raise _out_of_range(field, "segment", s, 0, n - 2, n)

    def open_waypoint(i: int, field: str, lo: int) -> int:
        """The planned index of user waypoint i (lo..n-1-lo allowed), not yet flown at from_time."""
        if not lo <= i <= n - 1 - lo:
            raise _out_of_range(field, "waypoint", i, lo, n - 1 - lo, n)
        j = int(idx[i])
        if j <= last:
            raise ChangeError(field, f"waypoint {i} is at or before from_time")
        return j

    for e in change.edits:
        if isinstance(e, MoveWaypoint):
            j = open_waypoint(e.index, "move.index", 0)
            moved[e.index] = np.asarray(e.position, dtype=float)
            edits.append(replace(e, index=j))
        elif isinstance(e, SetDuration):
            check_segment(e.segment, "duration.segment")
            edits.extend(spread(e.segment, e.duration))
        elif isinstance(e, SetCorridor):
            check_segment(e.segment, "corridor.segment")
            open_pieces = [p for p in wmap.pieces(e.segment) if p >= last]
            if not open_pieces:
                raise ChangeError("corridor.segment", f"segment {e.segment} is before from_time")
            edits.extend(SetCorridor(p, e.corridor) for p in open_pieces)
        elif isinstance(e, InsertWaypoint):
            if not 1 <= e.index <= n - 1:
                raise _out_of_range("insert.index", "waypoint", e.index, 1, n - 1, n)
            a, b = int(idx[e.index - 1]), int(idx[e.index])
            t0, t1 = float(times[a]), float(times[b])
            pos = np.asarray(e.position, dtype=float)
            t = e.time
            if t is None:  # as replan does for one segment: the user segment's time split by distance
                da = float(np.linalg.norm(pos - waypoints[a]))
                db = float(np.linalg.norm(waypoints[b] - pos))
                t = t0 + (t1 - t0) * (0.5 if da + db == 0.0 else da / (da + db))
            if not t0 < t < t1:
                raise ChangeError("insert.time", f"{t} must lie strictly between {t0} and {t1} (the times of "
                                                 f"waypoints {e.index - 1} and {e.index})")
            if t_from is not None and t <= t_from + TIME_EPS:
                raise ChangeError("insert.time", f"the new waypoint {e.index} at {t:g} s would be at or before "
                                                 "from_time")
            inner = np.arange(a + 1, b)
            if inner.size and float(np.min(np.abs(times[inner] - t))) <= TIME_EPS:
                raise ChangeError("insert.time", f"{t:g} s is the time of a knot on segment {e.index - 1}; "
                                                 "give another time")
            p = int(np.searchsorted(times, t))
            structural = ("insert", e.index, p)
            edits.append(replace(e, index=p, time=t))
        elif isinstance(e, RemoveWaypoint):
            j = open_waypoint(e.index, "remove.index", 1)
            structural = ("remove", e.index, j)
            edits.append(replace(e, index=j))
            if e.corridor is not None:  # the merged pieces j - 1, j get it from the removal itself
                lo, hi = int(idx[e.index - 1]), int(idx[e.index + 1])
                edits.extend(SetCorridor(p, e.corridor) for p in range(lo, hi) if p >= last and p not in (j - 1, j))
        elif isinstance(e, AppendWaypoints):
            appended += int(e.positions.shape[0])
            edits.append(e)
        else:
            edits.append(e)

    def position(u: int) -> FloatArray:
        return moved[u] if u in moved else np.asarray(waypoints[int(idx[u])], dtype=float)

    # knots follow the user geometry they lie on (module docstring); a structural edit's legs last
    for s in sorted({s for u in moved for s in (u - 1, u) if 0 <= s <= n - 2}):
        a, b = int(idx[s]), int(idx[s + 1])
        old = waypoints[b] - waypoints[a]
        span = float(old @ old)
        new_a, new_b = position(s), position(s + 1)
        for k in range(max(a + 1, frozen + 1), b):
            f = float((waypoints[k] - waypoints[a]) @ old) / span if span > 0.0 else \
                float((times[k] - times[a]) / (times[b] - times[a]))
            knot_to[k] = new_a + (new_b - new_a) * f
    if structural is not None:
        kind, u, p = structural
        # each new straight leg: (start position, start time, end position, end time)
        if kind == "insert":
            ins = next(e for e in edits if isinstance(e, InsertWaypoint))
            assert ins.time is not None
            legs = [(position(u - 1), float(times[idx[u - 1]]), ins.position, ins.time),
                    (ins.position, ins.time, position(u), float(times[idx[u]]))]
            knots = range(int(idx[u - 1]) + 1, int(idx[u]))
        else:
            legs = [(position(u - 1), float(times[idx[u - 1]]), position(u + 1), float(times[idx[u + 1]]))]
            knots = range(int(idx[u - 1]) + 1, int(idx[u + 1]))
        for k in knots:
            if k <= frozen or (k == p and kind == "remove"):
                continue
            tk = float(times[k])
            pa, ta, pb, tb = next(leg for leg in legs if leg[1] <= tk <= leg[3])
            knot_to[k] = pa + (pb - pa) * ((tk - ta) / (tb - ta))
    moves = [MoveWaypoint(k, pos) for k, pos in sorted(knot_to.items()) if not np.array_equal(pos, waypoints[k])]
    return PlannedChange(ChangeSet((*edits, *moves), change.from_time), wmap, structural, appended)
