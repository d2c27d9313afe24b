"""Which point a message's positions are measured from: the autopilot's local origin or home.

Positions inside the service are NED in the autopilot's local frame (the EKF origin, the
frame of LOCAL_POSITION_NED and of the setpoints). That origin is not the ground: PX4's
local z on the ground is often +1.5 m or more. A message may say `"origin": "home"`: its
positions are then relative to HOME_POSITION's local x, y, z (where the vehicle was armed or
booted) and are shifted here, once, on arrival, after the ENU/NED swap (`frames.py`): a
home-relative waypoint `p` becomes `home + p`. Obstacles are shifted with the message that
carries them (a mission's own, an `obstacles` or a `change` message's origin applies to
that message only). Half-spaces `A x <= b` become `A x <= b + A home`. A message may also say
`"origin": "fleet"`: its positions are in the fleet frame ([fleet] origin) and are mapped into
the local frame by where the autopilot's frame sits in it (companion.fleet), below.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from companion.geodesy import Placement
from companion.wire.frames import FloatArray

ORIGINS = ("local", "home", "fleet")


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


# One walk of each message's positions, whatever the frame they are given in (home or fleet).
def _map_obstacles(obj: dict[str, Any], region: Callable[[dict[str, Any]], dict[str, Any]]) -> dict[str, Any]:
    out = dict(obj)
    if "add" in obj:
        out["add"] = [region(r) for r in obj["add"]]
    return out


def _map_change(obj: dict[str, Any], points: Callable[[Any], list[list[float]]]) -> dict[str, Any]:
    out: dict[str, Any] = {}
    for kind, body in obj.items():
        if isinstance(body, dict):
            body = dict(body)
            for key in ("position", "waypoints"):
                if key in body:
                    body[key] = points(body[key])
        out[kind] = body
    return out


def obstacles_from_home(obj: dict[str, Any], home: FloatArray) -> dict[str, Any]:
    """A NED `obstacles` message with home-relative regions, in the local frame."""
    return _map_obstacles(obj, lambda r: _region(r, home))


def change_from_home(obj: dict[str, Any], home: FloatArray) -> dict[str, Any]:
    """A NED `change` message with home-relative positions, in the local frame."""
    return _map_change(obj, lambda p: _points(p, home))


# -- "origin": "fleet": positions in the fleet frame ([fleet] origin; companion.fleet) ------------
# A rigid map q = R p + t from local p to fleet q (companion.geodesy.Placement): points p = R^T (q - t),
# regions A q <= b -> (A R) p <= b - A t, the map box the local box holding its corners, the
# mission's initial/final jets (vectors) turned by R^T. Bounds stay as given: the local axes are
# turned from the fleet's by ~0.01 degrees per km of distance between the origins.


def _fleet_points(points: Any, pl: Placement) -> list[list[float]]:
    out: list[list[float]] = pl.to_local(points).tolist()
    return out


def _fleet_region(region: dict[str, Any], pl: Placement) -> dict[str, Any]:
    out = dict(region)
    if "A" in region:
        A, b = pl.halfspaces_to_local(region["A"], region["b"])
        out["A"], out["b"] = A.tolist(), b.tolist()
    if "vertices" in region:
        out["vertices"] = _fleet_points(region["vertices"], pl)
    return out


def scenario_from_fleet(obj: dict[str, Any], pl: Placement) -> dict[str, Any]:
    """A NED mission dict with fleet-frame positions, in the local frame."""
    out = dict(obj)
    out["waypoints"] = _fleet_points(obj["waypoints"], pl)
    if "obstacles" in obj:
        out["obstacles"] = [_fleet_region(r, pl) for r in obj["obstacles"]]
    if "map" in obj:
        lo, hi = pl.box_to_local(obj["map"]["min"], obj["map"]["max"])
        out["map"] = {"min": lo.tolist(), "max": hi.tolist()}
    for key in ("initial", "final"):
        if key in obj:
            out[key] = {k: pl.vectors_to_local(v).tolist() for k, v in obj[key].items()}
    return out


def obstacles_from_fleet(obj: dict[str, Any], pl: Placement) -> dict[str, Any]:
    """A NED `obstacles` message with fleet-frame regions, in the local frame."""
    return _map_obstacles(obj, lambda r: _fleet_region(r, pl))


def change_from_fleet(obj: dict[str, Any], pl: Placement) -> dict[str, Any]:
    """A NED `change` message with fleet-frame positions, in the local frame."""
    return _map_change(obj, lambda p: _fleet_points(p, pl))
