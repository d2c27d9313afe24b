"""Inbound Zenoh payloads -> a validated message dict: size, JSON, JSON Schema, [limits] and the
semantic checks the schema cannot say (lengths that must agree, times that must increase,
positions inside the geofence). A bad message raises `MessageError` naming the field (a JSON
path such as `waypoints[3][1]`) and the reason; companion.wire.messages turns the dict into
typed NED values.
"""

from __future__ import annotations

import dataclasses
import json
import re
from functools import cache
from importlib import resources
from typing import Any

import jsonschema
import numpy as np

from companion.config import LimitsConfig
from companion.wire.errors import MAX_QUOTE, MAX_REASON, MessageError, Oversized, bounded, quote
from companion.wire.frames import fmt_box, fmt_point
from companion.wire.jsonparse import check_values, json_path, parse_json
from planner_core import FloatArray


@cache
def schema(kind: str) -> dict[str, Any]:
    text = resources.files("companion.schemas").joinpath(f"{kind}.json").read_text("utf-8")
    doc: dict[str, Any] = json.loads(text)
    return doc


@cache
def validator(kind: str) -> jsonschema.protocols.Validator:
    doc = schema(kind)
    cls = jsonschema.validators.validator_for(doc)
    cls.check_schema(doc)
    validator: jsonschema.protocols.Validator = cls(doc)
    return validator


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
    errors = list(validator(kind).iter_errors(_schema_view(kind, obj)))
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

