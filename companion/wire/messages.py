"""Inbound Zenoh payloads -> validated, typed NED messages; the only place a wire error is raised.

Size, JSON, JSON Schema, semantic checks, then one conversion to NED and to typed values
(`MissionSpec`, `ObstacleUpdate`, a `Change`, `Command`). A bad message raises
`MessageError` naming the field (a JSON path such as `waypoints[3][1]`, in the message's own
indices) and the reason, with positions in the frame the operator used; `read` returns it
instead of raising, so the caller turns it into a `rejected` event and the flight goes on.
"""

from __future__ import annotations

import dataclasses
import json
import re
import time
from dataclasses import dataclass
from dataclasses import field as dc_field
from functools import cache
from importlib import resources
from typing import Any

import jsonschema
import numpy as np

from companion.config import Config, LimitsConfig
from companion.geodesy import Placement
from companion.wire.errors import (
    MAX_QUOTE,
    MAX_REASON,
    InternalError,
    MessageError,
    Oversized,
    bounded,
    quote,
)
from companion.wire.frames import (
    change_to_ned,
    fmt_box,
    fmt_point,
    obstacles_to_ned,
    plain,
    scenario_to_ned,
)
from companion.wire.jsonparse import check_values, json_path, parse_json
from companion.wire.keys import INBOUND
from companion.wire.origin import (
    change_from_fleet,
    change_from_home,
    obstacles_from_fleet,
    obstacles_from_home,
    scenario_from_fleet,
    scenario_from_home,
)
from planner_core import (
    Bounds,
    FieldError,
    FloatArray,
    Polytope,
    parse_polytope,
    polytope_vertices,
    rest_jet,
    vehicle_bound,
)

KINDS = INBOUND  # companion/wire/keys.py


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
    # and the hull's first use (it imports scipy.spatial: ~0.1 s) happens now, not in flight
    cube = [[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)]
    parse_region({"vertices": cube}, "warm-up")


def _points(value: Any) -> bool:
    """A non-empty list of [x, y, z] numbers (checked in C, not by the schema walker)."""
    if not isinstance(value, list) or not value:
        return False
    if not all(isinstance(p, list) and len(p) == 3 for p in value):
        return False
    try:
        arr = np.array(value, dtype=float)
    except (TypeError, ValueError, OverflowError):
        return False
    ok = bool(np.all(np.isfinite(arr)))
    # bools are numbers to numpy but not to JSON Schema
    return ok and not any(isinstance(x, bool) for p in value for x in p)


def _numbers(value: Any) -> bool:
    """A non-empty list of JSON numbers (int or float, not bool)."""
    return isinstance(value, list) and bool(value) and all(type(x) in (int, float) for x in value)


def _long_list(value: Any, n: int) -> bool:
    return isinstance(value, list) and len(value) > n


def _region_view(region: Any) -> Any:
    """An obstacle region with its well-formed arrays cut to the schema's minimum length."""
    if not isinstance(region, dict):
        return region
    out = dict(region)
    if _long_list(region.get("A"), 1) and _points(region["A"]):
        out["A"] = region["A"][:1]
    if _long_list(region.get("b"), 1) and _numbers(region["b"]):
        out["b"] = region["b"][:1]
    if _long_list(region.get("vertices"), 4) and _points(region["vertices"]):
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
    if kind == "mission":
        out = dict(obj)
        if _long_list(obj.get("waypoints"), 1) and _points(obj["waypoints"]):
            out["waypoints"] = obj["waypoints"][:1]
        if isinstance(obj.get("obstacles"), list):
            out["obstacles"] = [_region_view(r) for r in obj["obstacles"]]
        return out
    if kind == "change" and isinstance(obj.get("append"), dict):
        body = obj["append"]
        if _long_list(body.get("waypoints"), 1) and _points(body["waypoints"]):
            return {**obj, "append": {**body, "waypoints": body["waypoints"][:1]}}
    return obj


def _schema_reason(err: Any) -> str:
    """jsonschema's message, with the instance it quotes cut to MAX_QUOTE characters."""
    msg = str(err.message)
    try:
        inst = repr(err.instance)
    except Exception:  # pragma: no cover - a repr of parsed JSON does not fail
        inst = ""
    head = ""
    if len(inst) > MAX_QUOTE and msg.startswith(inst):
        head, msg = quote(inst), msg[len(inst):]
    # any other long quoted value (an unexpected key, say)
    return bounded(head + _LONG_QUOTED.sub(lambda m: quote(m.group(1)), msg), MAX_REASON)


_LONG_QUOTED = re.compile("'([^']{" + str(MAX_QUOTE + 1) + ",})'")


def validate(kind: str, obj: Any, lim: LimitsConfig | None = None) -> dict[str, Any]:
    check_values(obj, lim or LimitsConfig())
    errors = list(_validator(kind).iter_errors(_schema_view(kind, obj)))
    if errors:
        err = jsonschema.exceptions.best_match(errors)
        assert err is not None
        # oneOf errors are vague at the top; the deepest context names the field.
        while err.context:
            err = jsonschema.exceptions.best_match(err.context)
            assert err is not None
        raise MessageError(json_path(err.absolute_path), _schema_reason(err))
    assert isinstance(obj, dict)
    return obj


# What each command takes besides `command` (the schema says the same; this says it plainly).
COMMAND_FIELDS: dict[str, frozenset[str]] = {
    "arm": frozenset(), "takeoff": frozenset({"altitude", "origin"}), "start": frozenset(), "hold": frozenset(),
    "resume": frozenset(), "land": frozenset(), "abort": frozenset(), "disarm": frozenset(),
}


def _check_command_fields(obj: Any) -> None:
    if not isinstance(obj, dict) or not isinstance(obj.get("command"), str):
        return
    takes = COMMAND_FIELDS.get(obj["command"])
    if takes is None:
        return
    for k in obj:
        if k != "command" and k not in takes:
            others = [c for c, f in COMMAND_FIELDS.items() if k in f]
            hint = f" (only {', '.join(others)} does)" if others else ""
            raise MessageError(k, f"command {obj['command']!r} takes no {quote(k, 40)}{hint}")


def _check_counts(kind: str, obj: dict[str, Any], lim: LimitsConfig) -> None:
    """Array lengths against their [limits], on the schema-valid message."""
    def regions(items: list[Any], where: str) -> None:
        if len(items) > lim.max_obstacles:
            raise MessageError(where, f"{len(items)} obstacles exceed the limit of {lim.max_obstacles} "
                                      "([limits] max_obstacles)")
        for i, ob in enumerate(items):
            if len(ob.get("vertices", ())) > lim.max_obstacle_vertices:
                raise MessageError(f"{where}[{i}].vertices", f"{len(ob['vertices'])} vertices exceed the limit of "
                                   f"{lim.max_obstacle_vertices} ([limits] max_obstacle_vertices)")
            if len(ob.get("A", ())) > lim.max_obstacle_planes:
                raise MessageError(f"{where}[{i}].A", f"{len(ob['A'])} planes exceed the limit of "
                                   f"{lim.max_obstacle_planes} ([limits] max_obstacle_planes)")
            if "A" in ob and len(ob["A"]) != len(ob["b"]):
                raise MessageError(f"{where}[{i}].b", f"expected {len(ob['A'])} entries (one per row of A), got {len(ob['b'])}")

    if kind == "mission":
        if len(obj["waypoints"]) > lim.max_waypoints:
            raise MessageError("waypoints", f"{len(obj['waypoints'])} waypoints exceed the limit of "
                                            f"{lim.max_waypoints} ([limits] max_waypoints)")
        regions(obj.get("obstacles", []), "obstacles")
    elif kind == "obstacles":
        regions(obj.get("add", []), "add")
        if len(obj.get("remove", [])) > lim.max_obstacles_held:
            raise MessageError("remove", f"{len(obj['remove'])} ids exceed the limit of {lim.max_obstacles_held} "
                                         "([limits] max_obstacles_held)")
    elif kind == "change" and "append" in obj:
        body = obj["append"]
        if len(body["waypoints"]) > lim.max_waypoints:
            raise MessageError("append.waypoints", f"{len(body['waypoints'])} waypoints exceed the limit of "
                                                   f"{lim.max_waypoints} ([limits] max_waypoints)")


def check_durations(durations: Any, field: str, lim: LimitsConfig, waypoints: Any = None,
                    speed: FloatArray | None = None, first: int = 0, what: str = "duration") -> None:
    """Each segment duration (s) within [limits] min/max_segment_duration and, with the
    waypoints it joins (`waypoints[i]` -> `waypoints[i + 1]`) and the velocity bound per axis
    (`speed`), not shorter than any curve within that bound can fly: |dx| / v on every axis
    (the mean value theorem: a proven floor). `field` names the array; `first` is the index
    of its entry for the segment from waypoint 0 (1 for `times`)."""
    d = np.asarray(durations, dtype=float).reshape(-1)
    lo, hi = lim.min_segment_duration, lim.max_segment_duration
    for i in np.flatnonzero((d < lo) | (d > hi))[:1]:
        word = "shorter" if d[i] < lo else "longer"
        name = "min_segment_duration" if d[i] < lo else "max_segment_duration"
        raise MessageError(f"{field}[{int(i) + first}]" if field.endswith("s") else field,
                           f"a {what} of {d[i]:.6g} s is {word} than {lo if d[i] < lo else hi:g} s ([limits] {name})")
    if waypoints is None or speed is None:
        return
    wps = np.asarray(waypoints, dtype=float)
    need = np.max(np.abs(np.diff(wps, axis=0)) / np.asarray(speed, dtype=float), axis=1)
    short = np.flatnonzero(d < need * (1.0 - 1e-9))
    if short.size:
        i = int(short[0])
        length = float(np.linalg.norm(wps[i + 1] - wps[i]))
        raise MessageError(f"{field}[{i + first}]" if field.endswith("s") else field,
                           f"{d[i]:.6g} s is too short for the {length:.3g} m from waypoint {i} to "
                           f"{i + 1}: within the velocity bound no curve flies it in less than {need[i]:.3g} s")


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


def decode(kind: str, payload: bytes | Oversized, *, max_bytes: int | None = None, max_waypoints: int | None = None,
           max_obstacles: int | None = None, limits: LimitsConfig | None = None) -> dict[str, Any]:
    """Bytes -> validated dict, or MessageError. `limits` (default: [limits]'s defaults) with
    the keyword limits applied over it."""
    lim = limits or LimitsConfig()
    over = {k: v for k, v in (("max_message_bytes", max_bytes), ("max_waypoints", max_waypoints),
                              ("max_obstacles", max_obstacles)) if v is not None}
    if over:
        lim = dataclasses.replace(lim, **over)
    raw = parse_json(payload, lim.max_message_bytes, lim.max_number_chars)
    if kind == "command":
        _check_command_fields(raw)
    obj = validate(kind, raw, lim)
    _check_counts(kind, obj, lim)
    if kind == "mission":
        _check_lengths(obj)
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
    radius: float  # obstacles are inflated by this: the vehicle's radius + [planner] tracking_allowance
    start: str  # "current" | "first_waypoint"
    autostart: bool
    initial: FloatArray | None  # (5, 3) for start == "first_waypoint"
    frame: str = "ned"  # the operator's frame, for what we say back
    first_index: int = 0  # mission index of waypoints[0] (a resumed mission keeps its numbering)
    raw: dict[str, Any] = dc_field(default_factory=dict, compare=False)
    allowance: float = 0.0  # the tracking allowance within `radius`

    @property
    def corridor_map(self) -> tuple[FloatArray, FloatArray]:
        """The map box as the corridors take it (they shrink it by `radius`): widened by the
        tracking allowance, so that the fence keeps the margin it had (the vehicle's radius)
        and the allowance, meant for obstacles, does not push the plan off the floor."""
        return self.map_lo - self.allowance, self.map_hi + self.allowance


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
    origin: str = "ground"  # takeoff: the altitude is above the ground where the vehicle stands, or above home


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


def _vehicle_bound(value: dict[str, Any], field_name: str) -> tuple[FloatArray, FloatArray, float]:
    """{"horizontal": h, "up": u, "down": d} (or "vertical", optionally "box"): the planner's
    grammar (`planner_core.vehicle_bound`), in NED (up is -z)."""
    try:
        lo, hi, h = vehicle_bound(value, field_name, False)
    except FieldError as exc:
        raise MessageError(exc.field, exc.reason) from exc
    if np.any(lo >= 0) or np.any(hi <= 0):
        raise MessageError(f"{field_name}.box", "each interval must contain 0 (lo < 0 < hi)")
    return lo, hi, h


def bounds_from(obj: dict[str, Any] | None, cfg: Config) -> Bounds:
    b = cfg.planner.bounds
    base = Bounds.symmetric(b.velocity, b.acceleration, b.jerk, b.snap)
    lo, hi = base.lo.copy(), base.hi.copy()
    hor = np.full(4, np.inf)
    for row, name in enumerate(("velocity", "acceleration", "jerk", "snap")):
        if obj and name in obj:
            if isinstance(obj[name], dict):  # the vehicle form: replaces the order's limits
                lo[row], hi[row], hor[row] = _vehicle_bound(obj[name], f"bounds.{name}")
            else:
                lo[row], hi[row] = _bound(obj[name], f"bounds.{name}")
    return Bounds(lo, hi, horizontal=hor)


def parse_region(obj: dict[str, Any], field_name: str, lim: LimitsConfig | None = None) -> Polytope:
    """A schema-valid region to a Polytope: bounded, non-empty, solid (not flat), not huge,
    with at most [limits] max_obstacle_planes planes (its hull's faces for `vertices`)."""
    lim = lim or LimitsConfig()
    try:
        poly = parse_polytope({k: v for k, v in obj.items() if k != "id"}, field_name)
    except FieldError as exc:
        raise MessageError(exc.field, exc.reason) from None
    where = f"{field_name}.vertices" if "vertices" in obj else field_name
    if poly.A.shape[0] > lim.max_obstacle_planes:
        raise MessageError(where, f"its hull has {poly.A.shape[0]} faces, more than the limit of "
                                  f"{lim.max_obstacle_planes} ([limits] max_obstacle_planes)")
    try:
        # Corridors need bounded, non-empty obstacles: refuse others here, not mid-replan.
        verts = polytope_vertices(poly, field_name)
    except ValueError as exc:
        raise MessageError(field_name, str(exc).removeprefix(f"{field_name}: ")) from None
    extent = float(np.max(np.ptp(verts, axis=0)))
    if extent > lim.max_obstacle_extent:
        raise MessageError(where, f"obstacle spans {extent:.6g} m, more than {lim.max_obstacle_extent:g} m "
                                  "([limits] max_obstacle_extent)")
    centred = verts - verts.mean(axis=0)
    axes = np.linalg.svd(centred, full_matrices=False)[2] if verts.shape[0] >= 3 else np.eye(3)
    width = float(np.min(np.ptp(centred @ axes.T, axis=0))) if axes.shape[0] == 3 else 0.0
    if width < lim.min_obstacle_width:
        raise MessageError(where, f"obstacle is flat (thinnest width {width:.3g} m, less than "
                                  f"{lim.min_obstacle_width:g} m: [limits] min_obstacle_width)")
    return poly


def _regions(items: list[dict[str, Any]], where: str, lim: LimitsConfig, unnamed: str = "") -> tuple[tuple[str, Polytope], ...]:
    """Each region parsed, within [limits] decode_deadline for them all."""
    t0 = time.monotonic()
    out = []
    for i, ob in enumerate(items):
        out.append((str(ob.get("id", f"{unnamed}{i}")), parse_region(ob, f"{where}[{i}]", lim)))
        if time.monotonic() - t0 > lim.decode_deadline:
            raise MessageError(where, f"checking {len(items)} obstacles took longer than {lim.decode_deadline:g} s "
                                      f"(stopped after {i + 1}; [limits] decode_deadline)")
    return tuple(out)


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
    obstacles = _regions(obj.get("obstacles", []), "obstacles", cfg.limits, "mission-")
    initial = None
    if start == "first_waypoint":
        initial = rest_jet(wps[0])
        for row, name in enumerate(("velocity", "acceleration", "jerk", "snap"), start=1):
            if name in obj.get("initial", {}):
                initial[row] = obj["initial"][name]
    # obstacles are inflated by the vehicle's radius and by how far it may stray from the plan
    radius = max(cfg.planner.vehicle_radius, float(obj.get("vehicle_radius", 0.0))) + cfg.planner.tracking_allowance
    bounds = bounds_from(obj.get("bounds"), cfg)
    if durations is not None:
        speed = np.minimum(-bounds.lo[0], bounds.hi[0])
        check_durations(durations, "durations" if "durations" in obj else "times", cfg.limits, wps, speed,
                        first=0 if "durations" in obj else 1)
    return MissionSpec(
        id=str(obj["id"]), waypoints=wps, durations=durations, bounds=bounds,
        obstacles=obstacles, map_lo=map_lo, map_hi=map_hi, radius=radius, start=start,
        autostart=bool(obj.get("autostart", True)), initial=initial, frame=frame, raw=obj,
        allowance=cfg.planner.tracking_allowance,
    )


def obstacles_from_message(obj: dict[str, Any], frame: str = "ned", lim: LimitsConfig | None = None) -> ObstacleUpdate:
    """A schema-valid obstacles dict, already in NED, to an ObstacleUpdate (or MessageError)."""
    add = _regions(obj.get("add", []), "add", lim or LimitsConfig())
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
        check_durations([b["value"]], "duration.value", cfg.limits)
        body = DurationChange(int(b["index"]), float(b["value"]))
    elif "append" in obj:
        b = obj["append"]
        wps = np.asarray(b["waypoints"], dtype=float)
        check_geofence(wps, lo, hi, "append.waypoints", frame)
        if "durations" in b:
            check_durations(b["durations"], "append.durations", cfg.limits)
        body = AppendChange(wps, None if "durations" not in b else np.asarray(b["durations"], dtype=float))
    else:  # pragma: no cover - the schema requires one
        raise MessageError("", "no change given")
    return Change(body, frame)


def to_local(kind: str, obj: dict[str, Any], home: FloatArray | None,
             fleet: Placement | str | None = None) -> dict[str, Any]:
    """A NED message dict in the autopilot's local frame: shifted by `home` when it says
    `"origin": "home"` (see companion.wire.origin), refused while home is unknown; mapped from
    the fleet frame when it says `"origin": "fleet"` (`fleet`: the placement, the reason there
    is none yet, or None without [fleet] origin)."""
    if kind not in ("mission", "obstacles", "change"):
        return obj
    if obj.get("origin") == "fleet":
        if fleet is None:
            raise MessageError("origin", "a fleet-frame message (origin 'fleet') needs [fleet] origin in this "
                                         "companion's configuration, and it has none (docs/fleet.md)")
        if isinstance(fleet, str):
            raise MessageError("origin", f"a fleet-frame message (origin 'fleet') cannot be placed yet: {fleet}")
        to = {"mission": scenario_from_fleet, "obstacles": obstacles_from_fleet, "change": change_from_fleet}[kind]
        return to(obj, fleet)
    if obj.get("origin", "local") != "home":
        return obj
    if home is None or not np.all(np.isfinite(home)):
        raise MessageError("origin", "a home-relative message (origin 'home') cannot be placed yet: the autopilot "
                                     "has not reported HOME_POSITION (requested at link-up); send positions in "
                                     "its local frame (origin 'local', the default) or wait for home")
    shift = {"mission": scenario_from_home, "obstacles": obstacles_from_home, "change": change_from_home}[kind]
    return shift(obj, np.asarray(home, dtype=float))


def fence_at_home(cfg: Config, home: FloatArray | None) -> Config:
    """`cfg` with its geofence box in the local frame: shifted by home for `[geofence] origin =
    "home"` once home is known (until then the local frame's origin stands for home)."""
    if cfg.geofence.origin != "home" or home is None or not np.all(np.isfinite(home)):
        return cfg
    h = np.asarray(home, dtype=float)
    lo, hi = np.asarray(cfg.geofence.min) + h, np.asarray(cfg.geofence.max) + h
    fence = dataclasses.replace(cfg.geofence, min=(float(lo[0]), float(lo[1]), float(lo[2])),
                                max=(float(hi[0]), float(hi[1]), float(hi[2])))
    return dataclasses.replace(cfg, geofence=fence)


NOT_READY = ("the autopilot is not ready: it reports HOME_POSITION at its local origin (PX4 does so until its "
             "estimator is ready, ~40 s after boot), so the geofence, which follows home ([geofence] origin = "
             "\"home\"), cannot be placed yet; send the mission again once status `home` is set")


def read(kind: str, payload: bytes | Oversized, cfg: Config, home: FloatArray | None = None, *,
         home_pending: bool = False, fleet: Placement | str | None = None) -> Message | MessageError:
    """Bytes -> a typed NED message in the autopilot's local frame, or the MessageError that
    says why not. `home`: HOME_POSITION's local position, for messages with `"origin":
    "home"`; `fleet`: where the local frame sits in the fleet frame, for `"origin": "fleet"`
    (companion.fleet.FleetFrame.for_messages). Never raises: anything unforeseen comes back as an `InternalError` (a rejection
    the service also reports as an `error` event)."""
    try:
        obj = decode(kind, payload, limits=cfg.limits)
        frame = str(obj.get("frame", "ned"))
        if kind == "mission" and home_pending and home is None and cfg.geofence.origin == "home":
            return MessageError("", NOT_READY)
        cfg = fence_at_home(cfg, home)
        try:
            if kind == "mission":
                return mission_from_message(to_local(kind, scenario_to_ned(obj), home, fleet), cfg, frame)
            if kind == "obstacles":
                return obstacles_from_message(to_local(kind, obstacles_to_ned(obj), home, fleet), frame, cfg.limits)
            if kind == "change":
                return change_from_message(to_local(kind, change_to_ned(obj), home, fleet), cfg, frame)
        except MessageError as exc:
            if obj.get("origin") == "fleet" and exc.field != "origin" and isinstance(fleet, Placement):
                off = ", ".join(f"{plain(v):g}" for v in fleet.offset)
                raise MessageError(exc.field, f"{exc.reason} (local frame: the message's fleet-frame positions "
                                              f"less the local origin's place in the fleet frame, [{off}] NED)") from None
            if obj.get("origin") != "home" or exc.field == "origin" or home is None:
                raise
            # positions in reasons are local: say how they relate to what was sent
            raise MessageError(exc.field, f"{exc.reason} (local frame: the message's home-relative positions "
                                          f"plus home {fmt_point(home)} NED)") from None
        if kind == "command":
            alt = obj.get("altitude")
            return Command(str(obj["command"]), None if alt is None else float(alt), str(obj.get("origin", "ground")))
        return MessageError("", f"unknown message kind {quote(kind, 40)}")
    except MessageError as exc:
        return exc
    except RecursionError:
        return MessageError("", "nested too deeply ([limits] max_depth)")
    except MemoryError:
        return InternalError("", "out of memory while decoding")
    except Exception as exc:  # the last resort: a bug here must never stop the service
        return InternalError("", f"internal error while decoding: {type(exc).__name__}: {quote(str(exc))}")
