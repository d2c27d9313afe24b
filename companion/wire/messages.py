"""Inbound Zenoh payloads -> validated, typed NED messages; the only place a wire error is raised.

Size, JSON, JSON Schema, semantic checks, then one conversion to NED and to typed values
(`MissionSpec`, `ObstacleUpdate`, a `Change`, `Command`). A bad message raises
`MessageError` naming the field (a JSON path such as `waypoints[3][1]`, in the message's own
indices) and the reason, with positions in the frame the operator used; `read` returns it
instead of raising, so the caller turns it into a `rejected` event and the flight goes on.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass
from dataclasses import field as dc_field
from functools import cache
from importlib import resources
from typing import Any

import jsonschema
import numpy as np

from companion.config import Config
from companion.wire.frames import (
    change_to_ned,
    fmt_box,
    fmt_point,
    obstacles_to_ned,
    scenario_to_ned,
)
from planner_core import (
    Bounds,
    FieldError,
    FloatArray,
    Polytope,
    parse_polytope,
    polytope_vertices,
    rest_jet,
)

KINDS = ("mission", "obstacles", "change", "command")


class MessageError(FieldError):
    """A rejected message; `field` is a JSON path ('' for the whole payload)."""

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(field, reason)
        self.args = (f"{field or 'payload'}: {reason}",)


@cache
def schema(kind: str) -> dict[str, Any]:
    text = resources.files("companion.schemas").joinpath(f"{kind}.json").read_text("utf-8")
    doc: dict[str, Any] = json.loads(text)
    return doc


@cache
def _validator(kind: str) -> jsonschema.protocols.Validator:
    doc = schema(kind)
    cls = jsonschema.validators.validator_for(doc)
    cls.check_schema(doc)
    validator: jsonschema.protocols.Validator = cls(doc)
    return validator


def warm_validators() -> None:
    """Build (and check) every schema validator once: the first build takes ~0.1 s."""
    for kind in KINDS:
        _validator(kind)


def json_path(parts: Any) -> str:
    out = ""
    for p in parts:
        out += f"[{p}]" if isinstance(p, int) else (f".{p}" if out else str(p))
    return out


def parse_json(payload: bytes, max_bytes: int) -> Any:
    if len(payload) > max_bytes:
        raise MessageError("", f"payload of {len(payload)} bytes exceeds the limit of {max_bytes}")
    try:
        text = payload.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise MessageError("", f"not UTF-8: {exc.reason} at byte {exc.start}") from None
    try:
        return json.loads(text)
    except json.JSONDecodeError as exc:
        raise MessageError("", f"malformed JSON: {exc.msg} at line {exc.lineno} column {exc.colno}") from None


def _check_finite(obj: Any, path: list[Any]) -> None:
    """NaN, Infinity and overflowing literals (1e999) parse to floats; name where."""
    if isinstance(obj, float) and not math.isfinite(obj):
        raise MessageError(json_path(path), f"non-finite number {obj} is not allowed")
    if isinstance(obj, list):
        for i, v in enumerate(obj):
            _check_finite(v, [*path, i])
    elif isinstance(obj, dict):
        for k, v in obj.items():
            _check_finite(v, [*path, k])


def _points(value: Any) -> bool:
    """A non-empty list of [x, y, z] numbers (checked in C, not by the schema walker)."""
    if not isinstance(value, list) or not value:
        return False
    if not all(isinstance(p, list) and len(p) == 3 for p in value):
        return False
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError):
        return False
    ok = bool(np.all(np.isfinite(arr)))
    # bools are numbers to numpy but not to JSON Schema
    return ok and not any(isinstance(x, bool) for p in value for x in p)


def _numbers(value: Any) -> bool:
    """A non-empty list of JSON numbers (int or float, not bool)."""
    return isinstance(value, list) and bool(value) and all(type(x) in (int, float) for x in value)


def _region_view(region: Any) -> Any:
    """An obstacle region with its well-formed arrays cut to the schema's minimum length."""
    if not isinstance(region, dict):
        return region
    out = dict(region)
    if len(region.get("A") or ()) > 1 and _points(region["A"]):
        out["A"] = region["A"][:1]
    if len(region.get("b") or ()) > 1 and _numbers(region["b"]):
        out["b"] = region["b"][:1]
    if len(region.get("vertices") or ()) > 4 and _points(region["vertices"]):
        out["vertices"] = region["vertices"][:4]  # the schema's minItems
    return out


def _schema_view(kind: str, obj: Any) -> Any:
    """The message with long, well-formed point lists cut short for the schema walk.

    JSON Schema validation is pure Python (~0.1 ms per waypoint, ~0.2 ms per plane of an
    obstacle: a pop-up's whole message took 1-2 ms); a valid (n, 3) array is checked with
    numpy instead. Malformed arrays are left whole so the schema names the exact element at
    fault. (A's and b's lengths are compared on the whole message afterwards.)
    """
    if not isinstance(obj, dict):
        return obj
    if kind == "obstacles" and isinstance(obj.get("add"), list):
        return {**obj, "add": [_region_view(r) for r in obj["add"]]}
    if kind == "mission" and len(obj.get("waypoints") or ()) > 1 and _points(obj["waypoints"]):
        return {**obj, "waypoints": obj["waypoints"][:1]}
    if kind == "change" and isinstance(obj.get("append"), dict):
        body = obj["append"]
        if len(body.get("waypoints") or ()) > 1 and _points(body["waypoints"]):
            return {**obj, "append": {**body, "waypoints": body["waypoints"][:1]}}
    return obj


def validate(kind: str, obj: Any) -> dict[str, Any]:
    _check_finite(obj, [])
    errors = list(_validator(kind).iter_errors(_schema_view(kind, obj)))
    if errors:
        err = jsonschema.exceptions.best_match(errors)
        assert err is not None
        # oneOf errors are vague at the top; the deepest context names the field.
        while err.context:
            err = jsonschema.exceptions.best_match(err.context)
            assert err is not None
        raise MessageError(json_path(err.absolute_path), err.message)
    assert isinstance(obj, dict)
    return obj


def _check_lengths(obj: dict[str, Any]) -> None:
    m = len(obj["waypoints"])
    for key in ("times", "durations"):
        if key in obj:
            want = m if key == "times" else m - 1
            if len(obj[key]) != want:
                raise MessageError(key, f"expected {want} entries for {m} waypoints, got {len(obj[key])}")
    if "times" in obj and np.any(np.diff(obj["times"]) <= 0):
        i = int(np.argmax(np.diff(obj["times"]) <= 0)) + 1
        raise MessageError(f"times[{i}]", "times must increase strictly")
    for key in ("obstacles",):
        for i, region in enumerate(obj.get(key, [])):
            if "A" in region and len(region["A"]) != len(region["b"]):
                raise MessageError(f"{key}[{i}].b", f"expected {len(region['A'])} entries (one per row of A), got {len(region['b'])}")


def check_geofence(points: Any, lo: Any, hi: Any, field: str, frame: str = "ned", what: str = "the geofence") -> None:
    """Every point (NED) inside the box [lo, hi] (NED); the first offender is named, with the
    point and the box in the operator's `frame`."""
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    outside = np.any((pts < np.asarray(lo)) | (pts > np.asarray(hi)), axis=1)
    if np.any(outside):
        i = int(np.argmax(outside))
        raise MessageError(
            f"{field}[{i}]",
            f"position {fmt_point(pts[i], frame)} ({frame.upper()}) is outside {what} "
            f"{fmt_box(lo, hi, frame)}",
        )


def check_point(point: Any, lo: Any, hi: Any, field: str, frame: str = "ned", what: str = "the geofence") -> None:
    """One point (NED) inside the box [lo, hi]; the message in the operator's `frame`."""
    p = np.asarray(point, dtype=float)
    if np.any(p < np.asarray(lo)) or np.any(p > np.asarray(hi)):
        raise MessageError(field, f"position {fmt_point(p, frame)} ({frame.upper()}) is outside {what} "
                           f"{fmt_box(lo, hi, frame)}")


def decode(kind: str, payload: bytes, *, max_bytes: int, max_waypoints: int = 10**6, max_obstacles: int = 10**6) -> dict[str, Any]:
    """Bytes -> validated dict, or MessageError."""
    obj = validate(kind, parse_json(payload, max_bytes))
    if kind == "mission":
        if len(obj["waypoints"]) > max_waypoints:
            raise MessageError("waypoints", f"{len(obj['waypoints'])} waypoints exceed the limit of {max_waypoints}")
        _check_lengths(obj)
    elif kind == "obstacles":
        if len(obj.get("add", [])) > max_obstacles:
            raise MessageError("add", f"{len(obj['add'])} obstacles exceed the limit of {max_obstacles}")
        for i, ob in enumerate(obj.get("add", [])):
            if "A" in ob and len(ob["A"]) != len(ob["b"]):
                raise MessageError(f"add[{i}].b", f"expected {len(ob['A'])} entries (one per row of A), got {len(ob['b'])}")
    elif kind == "change" and "append" in obj:
        body = obj["append"]
        if "durations" in body and len(body["durations"]) != len(body["waypoints"]):
            raise MessageError("append.durations", f"expected {len(body['waypoints'])} entries, got {len(body['durations'])}")
    return obj


# -- typed messages (NED) -----------------------------------------------------------------


@dataclass(frozen=True)
class MissionSpec:
    id: str
    waypoints: FloatArray  # (k, 3) NED goals
    durations: FloatArray | None  # (k-1,) or None: allocate
    bounds: Bounds
    obstacles: tuple[tuple[str, Polytope], ...]
    map_lo: FloatArray
    map_hi: FloatArray
    radius: float
    start: str  # "current" | "first_waypoint"
    autostart: bool
    initial: FloatArray | None  # (5, 3) for start == "first_waypoint"
    frame: str = "ned"  # the operator's frame, for what we say back
    first_index: int = 0  # mission index of waypoints[0] (a resumed mission keeps its numbering)
    raw: dict[str, Any] = dc_field(default_factory=dict, compare=False)


@dataclass(frozen=True)
class ObstacleUpdate:
    add: tuple[tuple[str, Polytope], ...]
    remove: tuple[str, ...]
    clear: bool
    frame: str = "ned"


@dataclass(frozen=True)
class MoveChange:
    index: int  # mission waypoint, as currently published
    position: FloatArray


@dataclass(frozen=True)
class InsertChange:
    index: int  # the new waypoint's index; the waypoint there and later ones move up by one
    position: FloatArray


@dataclass(frozen=True)
class RemoveChange:
    index: int


@dataclass(frozen=True)
class DurationChange:
    index: int  # segment index: from mission waypoint `index` to `index + 1`
    value: float


@dataclass(frozen=True)
class AppendChange:
    waypoints: FloatArray
    durations: FloatArray | None


ChangeBody = MoveChange | InsertChange | RemoveChange | DurationChange | AppendChange


@dataclass(frozen=True)
class Change:
    body: ChangeBody
    frame: str = "ned"

    @property
    def key(self) -> str:
        """The message's own name for the change (for field paths)."""
        return CHANGE_KEYS[type(self.body)]


CHANGE_KEYS: dict[type, str] = {MoveChange: "move_waypoint", InsertChange: "insert_waypoint",
                                RemoveChange: "remove_waypoint", DurationChange: "duration",
                                AppendChange: "append"}


@dataclass(frozen=True)
class Command:
    name: str
    altitude: float | None = None


Message = MissionSpec | ObstacleUpdate | Change | Command


def _bound(value: Any, field_name: str) -> tuple[FloatArray, FloatArray]:
    if isinstance(value, int | float):
        hi = np.full(3, float(value))
        return -hi, hi
    arr = np.asarray(value, dtype=float)
    if arr.shape == (2,):
        lo, hi = np.full(3, arr[0]), np.full(3, arr[1])
    else:
        lo, hi = arr[:, 0], arr[:, 1]
    if np.any(lo >= 0) or np.any(hi <= 0):
        raise MessageError(field_name, "each interval must contain 0 (lo < 0 < hi)")
    return lo, hi


def bounds_from(obj: dict[str, Any] | None, cfg: Config) -> Bounds:
    b = cfg.planner.bounds
    base = Bounds.symmetric(b.velocity, b.acceleration, b.jerk, b.snap)
    lo, hi = base.lo.copy(), base.hi.copy()
    for row, name in enumerate(("velocity", "acceleration", "jerk", "snap")):
        if obj and name in obj:
            lo[row], hi[row] = _bound(obj[name], f"bounds.{name}")
    return Bounds(lo, hi)


def parse_region(obj: dict[str, Any], field_name: str) -> Polytope:
    try:
        poly = parse_polytope({k: v for k, v in obj.items() if k != "id"}, field_name)
    except FieldError as exc:
        raise MessageError(exc.field, exc.reason) from None
    try:
        # Corridors need bounded, non-empty obstacles: refuse others here, not mid-replan.
        polytope_vertices(poly, field_name)
    except ValueError as exc:
        raise MessageError(field_name, str(exc).removeprefix(f"{field_name}: ")) from None
    return poly


def mission_from_message(obj: dict[str, Any], cfg: Config, frame: str = "ned") -> MissionSpec:
    """A schema-valid mission dict, already in NED, to a MissionSpec (or MessageError)."""
    wps = np.asarray(obj["waypoints"], dtype=float)
    lo_g, hi_g = np.asarray(cfg.geofence.min, dtype=float), np.asarray(cfg.geofence.max, dtype=float)
    check_geofence(wps, lo_g, hi_g, "waypoints", frame)
    start = obj.get("start", "current")
    if start == "first_waypoint" and len(wps) < 2:
        raise MessageError("waypoints", "start 'first_waypoint' needs at least 2 waypoints")
    durations = None
    if "durations" in obj:
        durations = np.asarray(obj["durations"], dtype=float)
    elif "times" in obj:
        durations = np.diff(np.asarray(obj["times"], dtype=float))
    map_lo, map_hi = lo_g, hi_g
    if "map" in obj:
        map_lo = np.maximum(lo_g, np.asarray(obj["map"]["min"], dtype=float))
        map_hi = np.minimum(hi_g, np.asarray(obj["map"]["max"], dtype=float))
        if np.any(map_lo >= map_hi):
            raise MessageError("map", "the map box does not overlap the geofence")
        check_geofence(wps, map_lo, map_hi, "waypoints", frame, "the map")
    obstacles = tuple(
        (str(o.get("id", f"mission-{i}")), parse_region(o, f"obstacles[{i}]"))
        for i, o in enumerate(obj.get("obstacles", []))
    )
    initial = None
    if start == "first_waypoint":
        initial = rest_jet(wps[0])
        for row, name in enumerate(("velocity", "acceleration", "jerk", "snap"), start=1):
            if name in obj.get("initial", {}):
                initial[row] = obj["initial"][name]
    radius = max(cfg.planner.vehicle_radius, float(obj.get("vehicle_radius", 0.0)))
    return MissionSpec(
        id=str(obj["id"]), waypoints=wps, durations=durations, bounds=bounds_from(obj.get("bounds"), cfg),
        obstacles=obstacles, map_lo=map_lo, map_hi=map_hi, radius=radius, start=start,
        autostart=bool(obj.get("autostart", True)), initial=initial, frame=frame, raw=obj,
    )


def obstacles_from_message(obj: dict[str, Any], frame: str = "ned") -> ObstacleUpdate:
    """A schema-valid obstacles dict, already in NED, to an ObstacleUpdate (or MessageError)."""
    add = tuple((str(ob["id"]), parse_region(ob, f"add[{i}]")) for i, ob in enumerate(obj.get("add", [])))
    return ObstacleUpdate(add, tuple(str(k) for k in obj.get("remove", [])), bool(obj.get("clear", False)), frame)


def change_from_message(obj: dict[str, Any], cfg: Config, frame: str = "ned") -> Change:
    """A schema-valid change dict, already in NED, to a Change (or MessageError). Positions
    are checked against the geofence here; against the mission's map when applied."""
    lo, hi = np.asarray(cfg.geofence.min, dtype=float), np.asarray(cfg.geofence.max, dtype=float)
    body: ChangeBody
    if "move_waypoint" in obj:
        b = obj["move_waypoint"]
        check_point(b["position"], lo, hi, "move_waypoint.position", frame)
        body = MoveChange(int(b["index"]), np.asarray(b["position"], dtype=float))
    elif "insert_waypoint" in obj:
        b = obj["insert_waypoint"]
        check_point(b["position"], lo, hi, "insert_waypoint.position", frame)
        body = InsertChange(int(b["index"]), np.asarray(b["position"], dtype=float))
    elif "remove_waypoint" in obj:
        body = RemoveChange(int(obj["remove_waypoint"]["index"]))
    elif "duration" in obj:
        b = obj["duration"]
        body = DurationChange(int(b["index"]), float(b["value"]))
    elif "append" in obj:
        b = obj["append"]
        wps = np.asarray(b["waypoints"], dtype=float)
        check_geofence(wps, lo, hi, "append.waypoints", frame)
        body = AppendChange(wps, None if "durations" not in b else np.asarray(b["durations"], dtype=float))
    else:  # pragma: no cover - the schema requires one
        raise MessageError("", "no change given")
    return Change(body, frame)


def read(kind: str, payload: bytes, cfg: Config) -> Message | MessageError:
    """Bytes -> a typed NED message, or the MessageError that says why not (never raises it)."""
    lim = cfg.limits
    try:
        obj = decode(kind, payload, max_bytes=lim.max_message_bytes, max_waypoints=lim.max_waypoints,
                     max_obstacles=lim.max_obstacles)
        frame = str(obj.get("frame", "ned"))
        if kind == "mission":
            return mission_from_message(scenario_to_ned(obj), cfg, frame)
        if kind == "obstacles":
            return obstacles_from_message(obstacles_to_ned(obj), frame)
        if kind == "change":
            return change_from_message(change_to_ned(obj), cfg, frame)
        if kind == "command":
            alt = obj.get("altitude")
            return Command(str(obj["command"]), None if alt is None else float(alt))
        return MessageError("", f"unknown message kind {kind!r}")
    except MessageError as exc:
        return exc
