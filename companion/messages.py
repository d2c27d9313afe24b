"""Inbound Zenoh payloads: size, JSON, JSON Schema, then semantic checks.

A bad message raises `MessageError` naming the field (a JSON path such as
`waypoints[3][1]`) and the reason; the caller turns that into a `rejected`
event and leaves the flight untouched.
"""

from __future__ import annotations

import json
import math
from functools import cache
from importlib import resources
from typing import Any

import jsonschema
import numpy as np

KINDS = ("mission", "obstacles", "change", "command")


class MessageError(ValueError):
    """A rejected message; `field` is a JSON path ('' for the whole payload)."""

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(f"{field or 'payload'}: {reason}")
        self.field = field
        self.reason = reason


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


def check_geofence(points: Any, lo: Any, hi: Any, field: str) -> None:
    """Every point (NED) inside the box [lo, hi]; the first offender is named."""
    pts = np.atleast_2d(np.asarray(points, dtype=float))
    outside = np.any((pts < np.asarray(lo)) | (pts > np.asarray(hi)), axis=1)
    if np.any(outside):
        i = int(np.argmax(outside))
        raise MessageError(
            f"{field}[{i}]",
            f"position {pts[i].tolist()} (NED) is outside the geofence {list(lo)}..{list(hi)}",
        )


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
