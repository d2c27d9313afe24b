"""Which point a message's positions are measured from: the autopilot's local origin or home.

Positions inside the service are NED in the autopilot's local frame (the EKF origin, the
frame of LOCAL_POSITION_NED and of the setpoints). That origin is not the ground: PX4's
local z on the ground is often +1.5 m or more. A message may say `"origin": "home"`: its
positions are then relative to HOME_POSITION's local x, y, z (where the vehicle was armed or
booted) and are shifted here, once, on arrival, after the ENU/NED swap (`frames.py`): a
home-relative waypoint `p` becomes `home + p`. Obstacles are shifted with the message that
carries them (a mission's own, an `obstacles` or a `change` message's origin applies to
that message only). Half-spaces `A x <= b` become `A x <= b + A home`.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from companion.wire.frames import FloatArray

ORIGINS = ("local", "home")


def _points(points: Any, home: FloatArray) -> list[list[float]]:
    out: list[list[float]] = (np.asarray(points, dtype=float) + home).tolist()
    return out


def _region(region: dict[str, Any], home: FloatArray) -> dict[str, Any]:
    out = dict(region)
    if "A" in region:
        A = np.asarray(region["A"], dtype=float)
        out["b"] = (np.asarray(region["b"], dtype=float) + A @ home).tolist()
    if "vertices" in region:
        out["vertices"] = _points(region["vertices"], home)
    return out


def scenario_from_home(obj: dict[str, Any], home: FloatArray) -> dict[str, Any]:
    """A NED mission dict with home-relative positions, in the local frame."""
    out = dict(obj)
    out["waypoints"] = _points(obj["waypoints"], home)
    if "obstacles" in obj:
        out["obstacles"] = [_region(r, home) for r in obj["obstacles"]]
    if "map" in obj:
        out["map"] = {"min": _points(obj["map"]["min"], home), "max": _points(obj["map"]["max"], home)}
    return out


def obstacles_from_home(obj: dict[str, Any], home: FloatArray) -> dict[str, Any]:
    """A NED `obstacles` message with home-relative regions, in the local frame."""
    out = dict(obj)
    if "add" in obj:
        out["add"] = [_region(r, home) for r in obj["add"]]
    return out


def change_from_home(obj: dict[str, Any], home: FloatArray) -> dict[str, Any]:
    """A NED `change` message with home-relative positions, in the local frame."""
    out: dict[str, Any] = {}
    for kind, body in obj.items():
        if isinstance(body, dict):
            body = dict(body)
            if "position" in body:
                body["position"] = _points(body["position"], home)
            if "waypoints" in body:
                body["waypoints"] = _points(body["waypoints"], home)
        out[kind] = body
    return out
