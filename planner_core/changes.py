"""Mission changes for local replanning, and their JSON form.

A change set is a dict (CHANGE.json) with any of these keys; every index
refers to the problem *as given* (before any split or edit). `replan` counts
every waypoint of the problem it is handed; the planner CLI's replan counts the
user's waypoints instead (knots absent) through the trajectory's
"waypoint_index" (`planner_core.indices.to_planned`). The companion
schema's spellings are accepted too ("move_waypoint", "insert_waypoint",
"remove_waypoint", duration {"index", "value"}); "description" is ignored.

    {"from_time": t,
     "move": {"index": j, "position": [x, y, z]}            (or a list of them),
     "duration": {"segment": s, "duration": d}             (or a list),
     "corridor": {"segment": s, "corridor": {"A":..,"b":..} | null}   (or a list),
     "obstacles": [polytope, ...],
     "insert": {"index": i, "position": [..], "time": t (optional)},
     "remove": {"index": i, "corridor": polytope (optional)},
     "append": {"waypoints": [[..], ..], "durations": [..] (optional),
                "corridors": [polytope | null, ..] (optional), "final": {...} (optional)}}

A polytope is {"A": [[..]], "b": [..]}, {"vertices": [[..], ..]},
{"min": [..], "max": [..]} or {"center": [..], "size": [..]} (axis-aligned boxes).
At most one of insert/remove per change set: indices of a second structural
edit would be ambiguous.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from planner_core.errors import FieldError
from planner_core.problem import FloatArray, Polytope


class ChangeError(FieldError):
    """Invalid change description; `.field` names the offending entry."""


@dataclass(frozen=True)
class MoveWaypoint:
    index: int
    position: FloatArray  # (3,)


@dataclass(frozen=True)
class SetDuration:
    segment: int
    duration: float


@dataclass(frozen=True)
class SetCorridor:
    segment: int
    corridor: Polytope | None


@dataclass(frozen=True)
class AddObstacles:
    obstacles: tuple[Polytope, ...]


@dataclass(frozen=True)
class InsertWaypoint:
    index: int  # index of the new waypoint, 1 .. m-1
    position: FloatArray
    time: float | None = None  # None: split the old segment's time by distance


@dataclass(frozen=True)
class RemoveWaypoint:
    index: int  # 1 .. m-2
    corridor: Polytope | None = None  # corridor of the merged segment, if known


@dataclass(frozen=True)
class AppendWaypoints:
    positions: FloatArray  # (k, 3)
    durations: FloatArray | None = None  # (k,); None: allocate from the bounds
    corridors: tuple[Polytope | None, ...] | None = None
    final: FloatArray | None = None  # (5, 3) terminal jet; None: rest


Edit = MoveWaypoint | SetDuration | SetCorridor | AddObstacles | InsertWaypoint | RemoveWaypoint | AppendWaypoints


@dataclass(frozen=True)
class ChangeSet:
    edits: tuple[Edit, ...]
    from_time: float | None = None


# --- parsing -----------------------------------------------------------------


def _vector(value: Any, field: str, size: int = 3) -> FloatArray:
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError) as exc:
        raise ChangeError(field, f"expected {size} numbers") from exc
    if arr.shape != (size,):
        raise ChangeError(field, f"expected {size} numbers, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ChangeError(field, "must be finite")
    return arr


def _number(value: Any, field: str, *, positive: bool = False) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise ChangeError(field, f"expected a number, got {type(value).__name__}")
    x = float(value)
    if not math.isfinite(x):
        raise ChangeError(field, "must be finite")
    if positive and x <= 0.0:
        raise ChangeError(field, f"must be > 0, got {x}")
    return x


def _index(value: Any, field: str) -> int:
    if isinstance(value, bool) or not isinstance(value, int):
        raise ChangeError(field, f"expected an integer index, got {value!r}")
    if value < 0:
        raise ChangeError(field, f"must be >= 0, got {value}")
    return int(value)


def _dict(value: Any, field: str) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise ChangeError(field, f"expected an object, got {type(value).__name__}")
    return value


def _items(value: Any, field: str) -> list[tuple[str, dict[str, Any]]]:
    if isinstance(value, list):
        return [(f"{field}[{i}]", _dict(v, f"{field}[{i}]")) for i, v in enumerate(value)]
    return [(field, _dict(value, field))]


def _require(obj: dict[str, Any], key: str, field: str) -> Any:
    if key not in obj:
        raise ChangeError(f"{field}.{key}", "missing")
    return obj[key]


def parse_polytope(obj: Any, field: str) -> Polytope:
    """A polytope from {"A","b"}, {"vertices"}, {"min","max"} or {"center","size"}."""
    d = _dict(obj, field)
    if "A" in d:
        try:
            A = np.asarray(d["A"], dtype=float)
            b = np.asarray(_require(d, "b", field), dtype=float)
        except (TypeError, ValueError) as exc:
            raise ChangeError(field, "A and b must be numeric arrays") from exc
        if A.ndim != 2 or A.shape[1] != 3 or b.shape != (A.shape[0],):
            raise ChangeError(field, f"A must be (k, 3) and b (k,), got {A.shape} and {b.shape}")
        if not (np.all(np.isfinite(A)) and np.all(np.isfinite(b))):
            raise ChangeError(field, "A and b must be finite")
        return Polytope(A, b)
    if "vertices" in d:
        try:
            verts = np.asarray(d["vertices"], dtype=float)
        except (TypeError, ValueError) as exc:
            raise ChangeError(f"{field}.vertices", "must be numeric") from exc
        if verts.ndim != 2 or verts.shape[1] != 3 or verts.shape[0] < 4:
            raise ChangeError(f"{field}.vertices", f"need >= 4 points of 3 coordinates, got {verts.shape}")
        from planner_core.geometry import polytope_from_vertices

        try:
            return polytope_from_vertices(verts)
        except ValueError as exc:
            raise ChangeError(f"{field}.vertices", str(exc)) from exc
    if "min" in d or "max" in d:
        lo = _vector(_require(d, "min", field), f"{field}.min")
        hi = _vector(_require(d, "max", field), f"{field}.max")
        return box(lo, hi, field)
    if "center" in d or "size" in d:
        c = _vector(_require(d, "center", field), f"{field}.center")
        s = _vector(_require(d, "size", field), f"{field}.size")
        return box(c - s / 2.0, c + s / 2.0, field)
    raise ChangeError(field, "expected keys A/b, vertices, min/max or center/size")


def box(lo: FloatArray, hi: FloatArray, field: str = "box") -> Polytope:
    if np.any(hi <= lo):
        raise ChangeError(field, f"empty box: min {lo.tolist()} max {hi.tolist()}")
    eye = np.eye(3)
    return Polytope(np.vstack([eye, -eye]), np.concatenate([hi, -lo]))


def _parse_append(d: dict[str, Any], field: str) -> AppendWaypoints:
    try:
        pts = np.asarray(_require(d, "waypoints", field), dtype=float)
    except (TypeError, ValueError) as exc:
        raise ChangeError(f"{field}.waypoints", "must be numeric") from exc
    if pts.ndim != 2 or pts.shape[1] != 3 or pts.shape[0] == 0:
        raise ChangeError(f"{field}.waypoints", f"expected a non-empty list of [x, y, z], got shape {pts.shape}")
    if not np.all(np.isfinite(pts)):
        raise ChangeError(f"{field}.waypoints", "must be finite")
    durations = None
    if d.get("durations") is not None:
        raw = d["durations"]
        if not isinstance(raw, list) or len(raw) != pts.shape[0]:
            raise ChangeError(f"{field}.durations", f"expected {pts.shape[0]} durations")
        durations = np.array([_number(v, f"{field}.durations[{i}]", positive=True) for i, v in enumerate(raw)])
    corridors = None
    if d.get("corridors") is not None:
        raw = d["corridors"]
        if not isinstance(raw, list) or len(raw) != pts.shape[0]:
            raise ChangeError(f"{field}.corridors", f"expected {pts.shape[0]} entries (one per new segment)")
        corridors = tuple(
            None if c is None else parse_polytope(c, f"{field}.corridors[{i}]") for i, c in enumerate(raw)
        )
    final = None
    if d.get("final") is not None:
        fd = _dict(d["final"], f"{field}.final")
        final = np.zeros((5, 3))
        final[0] = pts[-1]
        for row, name in enumerate(("velocity", "acceleration", "jerk", "snap"), start=1):
            if name in fd:
                final[row] = _vector(fd[name], f"{field}.final.{name}")
    return AppendWaypoints(pts, durations, corridors, final)


def parse_change(obj: Any) -> ChangeSet:
    """Parse CHANGE.json; raises ChangeError naming the field on bad input."""
    d = {k: v for k, v in _dict(obj, "change").items() if k not in ("description", "comment")}
    # the spellings of examples/scenario2_move.json and companion/schemas/change.json
    for alias, key in (("move_waypoint", "move"), ("insert_waypoint", "insert"), ("remove_waypoint", "remove")):
        if alias in d:
            if key in d:
                raise ChangeError(alias, f"give either {key} or {alias}")
            d[key] = d.pop(alias)
    known = {"from_time", "move", "duration", "corridor", "obstacles", "insert", "remove", "append"}
    unknown = sorted(set(d) - known)
    if unknown:
        raise ChangeError(unknown[0], f"unknown change key (expected one of {sorted(known)})")
    edits: list[Edit] = []
    for f, e in _items(d.get("move", []), "move"):
        edits.append(MoveWaypoint(_index(_require(e, "index", f), f"{f}.index"), _vector(_require(e, "position", f), f"{f}.position")))
    for f, e in _items(d.get("duration", []), "duration"):
        # {"segment", "duration"}, or the companion schema's {"index", "value"}
        seg_key = "index" if "index" in e and "segment" not in e else "segment"
        val_key = "value" if "value" in e and "duration" not in e else "duration"
        edits.append(
            SetDuration(
                _index(_require(e, seg_key, f), f"{f}.{seg_key}"),
                _number(_require(e, val_key, f), f"{f}.{val_key}", positive=True),
            )
        )
    for f, e in _items(d.get("corridor", []), "corridor"):
        raw = _require(e, "corridor", f)
        poly = None if raw is None else parse_polytope(raw, f"{f}.corridor")
        edits.append(SetCorridor(_index(_require(e, "segment", f), f"{f}.segment"), poly))
    if "obstacles" in d:
        raw = d["obstacles"]
        if not isinstance(raw, list) or not raw:
            raise ChangeError("obstacles", "expected a non-empty list of polytopes")
        edits.append(AddObstacles(tuple(parse_polytope(o, f"obstacles[{i}]") for i, o in enumerate(raw))))
    if "insert" in d and "remove" in d:
        raise ChangeError("insert", "insert and remove in one change set are ambiguous; send two changes")
    if "insert" in d:
        e = _dict(d["insert"], "insert")
        t = e.get("time")
        edits.append(
            InsertWaypoint(
                _index(_require(e, "index", "insert"), "insert.index"),
                _vector(_require(e, "position", "insert"), "insert.position"),
                None if t is None else _number(t, "insert.time"),
            )
        )
    if "remove" in d:
        e = _dict(d["remove"], "remove")
        corr = e.get("corridor")
        edits.append(
            RemoveWaypoint(
                _index(_require(e, "index", "remove"), "remove.index"),
                None if corr is None else parse_polytope(corr, "remove.corridor"),
            )
        )
    if "append" in d:
        edits.append(_parse_append(_dict(d["append"], "append"), "append"))
    from_time = None if d.get("from_time") is None else _number(d["from_time"], "from_time")
    if not edits and from_time is None:
        raise ChangeError("change", "no change given")
    return ChangeSet(tuple(edits), from_time)


def as_change_set(change: ChangeSet | Edit | Sequence[Edit]) -> ChangeSet:
    if isinstance(change, ChangeSet):
        return change
    if isinstance(change, Sequence):
        return ChangeSet(tuple(change))
    return ChangeSet((change,))
