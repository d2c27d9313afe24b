"""One reader of a `change`: a typed Change resolved against the route being flown.

Indices in a change refer to the mission as currently published (mission waypoint i is the
route waypoint labelled i; inserts and removals renumber the later ones). `resolve` reads a
change once and gives both forms the replanning needs: the planner_core edits for a local
replan (in the route's own indices: the route handed in must be the one the local replan
starts from, i.e. already trimmed) and the whole edited waypoint/time/label arrays for a
replan of the remainder. What cannot be done is a `Refused` naming the field and why.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from companion.route import Route, allocate_durations
from companion.wire.frames import fmt_box, fmt_point
from companion.wire.messages import (
    AppendChange,
    Change,
    DurationChange,
    InsertChange,
    MoveChange,
    RemoveChange,
)
from planner_core import (
    AppendWaypoints,
    Bounds,
    FloatArray,
    InsertWaypoint,
    MoveWaypoint,
    RemoveWaypoint,
    SetDuration,
)


@dataclass(frozen=True)
class LocalEdit:
    """planner_core edits in route indices plus how they renumber the labels (picklable)."""

    edits: tuple[Any, ...]
    description: str
    # ("same",) | ("insert", route index, mission index) | ("remove", route index) | ("append", first, count)
    labels: tuple[Any, ...] = ("same",)

    def relabel(self, labels: FloatArray, wp: Any) -> FloatArray:
        """New labels; `wp` maps a route index before the split to one after it."""
        kind = self.labels[0]
        if kind == "insert":
            k = wp(self.labels[1])
            out = np.insert(labels, k, float(self.labels[2]))
            out[k + 1 :] = np.where(out[k + 1 :] >= 0, out[k + 1 :] + 1, out[k + 1 :])
            return out
        if kind == "remove":
            k = wp(self.labels[1])
            out = np.delete(labels, k)
            out[k:] = np.where(out[k:] >= 0, out[k:] - 1, out[k:])
            return out
        if kind == "append":
            return np.concatenate([labels, self.labels[1] + np.arange(self.labels[2], dtype=float)])
        return labels


@dataclass(frozen=True)
class Resolved:
    local: LocalEdit | None  # None: not expressible as a local edit (the remainder is replanned)
    waypoints: FloatArray  # the edited route, whole
    times: FloatArray
    labels: FloatArray
    description: str
    allocate: bool = False  # the remainder's durations are chosen again (replan_remainder)
    sets_times: bool = False  # the change gives times (a set duration, appended durations)


@dataclass(frozen=True)
class Refused:
    field: str
    reason: str


def route_index(route: Route, index: int) -> int | None:
    """The route index of mission waypoint `index` (None: not in the route)."""
    hits = np.nonzero(route.labels == index)[0]
    return int(hits[0]) if len(hits) else None


def remaining_indices(route: Route, t: float) -> list[int]:
    return sorted(int(x) for x, tm in zip(route.labels, route.times, strict=True) if x >= 0 and tm > t)


def _ahead(route: Route, index: int, t_split: float, field: str) -> int | Refused:
    i = route_index(route, index)
    if i is None or route.times[i] <= t_split:
        passed = i is not None or (route.labels.size and index <= int(np.max(route.labels)))
        why = "has already been passed" if passed else "is not in the mission"
        return Refused(field, f"mission waypoint {index} {why} (still ahead: {remaining_indices(route, t_split)})")
    return i


def _retime(points: FloatArray, times: FloatArray, i: int, bounds: Bounds) -> FloatArray:
    """Re-allocate the segments touching waypoint i and shift later times by the difference."""
    lo, hi = max(i - 1, 0), min(i + 1, len(points) - 1)
    d = allocate_durations(points[lo : hi + 1], bounds)
    new = times.copy()
    new[lo + 1 : hi + 1] = times[lo] + np.cumsum(d)
    new[hi + 1 :] = times[hi + 1 :] + (new[hi] - times[hi])
    return new


def _outside_map(route: Route, points: FloatArray, field: str, frame: str) -> Refused | None:
    m = route.mission
    pts = np.atleast_2d(points)
    out = np.any((pts < m.map_lo) | (pts > m.map_hi), axis=1)
    if not np.any(out):
        return None
    k = int(np.argmax(out))
    where = f"{field}[{k}]" if points.ndim == 2 else field
    return Refused(where, f"position {fmt_point(pts[k], frame)} ({frame.upper()}) is outside the mission's map "
                   f"{fmt_box(m.map_lo, m.map_hi, frame)}")


def resolve_planned(route: Route, change: Change, t_split: float, allocated: bool) -> Resolved | Refused:
    """`resolve` as the navigator applies it. The change is read between mission waypoints,
    without the planner's knots (with knots dropped there is no local edit: its indices would
    count them). `allocated`: the mission gave no durations and the planner chose them, so the
    remainder is allocated again, unless the change gives times (a set duration, appended
    durations): those are kept."""
    view = route.without_knots()
    out = resolve(view, change, t_split)
    if isinstance(out, Refused):
        return out
    body = change.body
    times = isinstance(body, DurationChange) or (isinstance(body, AppendChange) and body.durations is not None)
    return replace(out, local=out.local if view is route else None, allocate=allocated and not times,
                   sets_times=times)


def resolve(route: Route, change: Change, t_split: float) -> Resolved | Refused:
    """Read `change` against `route` (NED, mission indices as published) at the split time."""
    wps, tms, lab = route.waypoints.copy(), route.times.copy(), route.labels.copy()
    bounds, frame, body, key = route.mission.bounds, change.frame, change.body, change.key
    if isinstance(body, MoveChange):
        if (bad := _outside_map(route, body.position, f"{key}.position", frame)) is not None:
            return bad
        i = _ahead(route, body.index, t_split, f"{key}.index")
        if isinstance(i, Refused):
            return i
        wps[i] = body.position
        what = f"moved waypoint {body.index}"
        return Resolved(LocalEdit((MoveWaypoint(i, body.position.copy()),), what), wps, tms, lab, what)
    if isinstance(body, DurationChange):
        i = _ahead(route, body.index + 1, t_split, f"{key}.index")
        if isinstance(i, Refused):
            return i
        if i == 0 or lab[i - 1] not in (body.index, -1):
            return Refused(f"{key}.index", f"segment {body.index} is not in the remaining mission")
        # A segment being flown starts at the last split point: the new duration counts from there.
        start = tms[i - 1]
        if start + body.value <= t_split + 0.05:
            return Refused(f"{key}.value", f"a duration of {body.value:g} s ends before the replanning point")
        speed = np.minimum(-bounds.lo[0], bounds.hi[0])
        need = float(np.max(np.abs(wps[i] - wps[i - 1]) / speed))
        if body.value < need * (1.0 - 1e-9):
            return Refused(f"{key}.value", f"{body.value:g} s is too short for the "
                           f"{float(np.linalg.norm(wps[i] - wps[i - 1])):.3g} m left of segment {body.index}: within "
                           f"the velocity bound no curve flies it in less than {need:.3g} s")
        tms[i:] += start + body.value - tms[i]
        what = f"segment {body.index} duration set to {body.value:g} s"
        local = LocalEdit((SetDuration(i - 1, body.value),), what) if lab[i - 1] == body.index else None
        return Resolved(local, wps, tms, lab, what)
    if isinstance(body, InsertChange):
        if (bad := _outside_map(route, body.position, f"{key}.position", frame)) is not None:
            return bad
        i = _ahead(route, body.index, t_split, f"{key}.index")
        if isinstance(i, Refused):
            if route_index(route, body.index) is None and body.index == int(np.max(lab, initial=-1)) + 1:
                return Refused(f"{key}.index", f"mission waypoint {body.index} would follow the last one: use append")
            return i
        what = f"inserted waypoint {body.index}"
        local = LocalEdit((InsertWaypoint(i, body.position.copy()),), what, ("insert", i, body.index)) if i > 0 else None
        wps = np.insert(wps, i, body.position, axis=0)
        tms = np.insert(tms, i, tms[i])
        lab = np.insert(lab, i, body.index)
        lab[i + 1 :] = np.where(lab[i + 1 :] >= 0, lab[i + 1 :] + 1, lab[i + 1 :])
        tms = _retime(wps, tms, i, bounds)
        return Resolved(local, wps, tms, lab, what)
    if isinstance(body, RemoveChange):
        i = _ahead(route, body.index, t_split, f"{key}.index")
        if isinstance(i, Refused):
            return i
        ahead = remaining_indices(route, t_split)
        if len(ahead) <= 1:
            return Refused(f"{key}.index", f"cannot remove mission waypoint {body.index}: it is the only one left")
        what = f"removed waypoint {body.index}"
        local = LocalEdit((RemoveWaypoint(i),), what, ("remove", i)) if 0 < i < len(lab) - 1 else None
        wps, tms, lab = np.delete(wps, i, axis=0), np.delete(tms, i), np.delete(lab, i)
        lab[i:] = np.where(lab[i:] >= 0, lab[i:] - 1, lab[i:])
        tms = _retime(wps, tms, min(i, len(wps) - 1), bounds)
        return Resolved(local, wps, tms, lab, what)
    if isinstance(body, AppendChange):
        if (bad := _outside_map(route, body.waypoints, f"{key}.waypoints", frame)) is not None:
            return bad
        new = body.waypoints
        d = body.durations if body.durations is not None else allocate_durations(np.vstack([wps[-1:], new]), bounds)
        nxt = int(np.max(lab)) + 1 if np.any(lab >= 0) else 0
        what = f"appended {len(new)} waypoints"
        local = LocalEdit((AppendWaypoints(new.copy(), None if body.durations is None else body.durations.copy()),),
                          what, ("append", float(nxt), len(new)))
        start = max(tms[-1], t_split)
        wps = np.vstack([wps, new])
        tms = np.concatenate([tms, start + np.cumsum(d)])
        lab = np.concatenate([lab, nxt + np.arange(len(new), dtype=float)])
        return Resolved(local, wps, tms, lab, what)
    raise TypeError(f"not a change: {body!r}")  # a bug: the decoder makes only these
