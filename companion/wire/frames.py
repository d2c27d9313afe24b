"""ENU <-> NED at the service boundary.

Everything inside the service is NED (the autopilot's local frame). A message
in ENU is converted once, on arrival, and never again. The map is the
permutation-with-sign P = [[0,1,0],[1,0,0],[0,0,-1]], which is its own inverse,
so the same functions convert both ways.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]

P = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def swap_points(points: Any) -> FloatArray:
    """Points or vectors (..., 3) from one frame to the other."""
    out: FloatArray = np.asarray(points, dtype=float) @ P.T
    return out


def swap_halfspaces(A: Any) -> FloatArray:
    """Rows of A x <= b from one frame to the other (b is unchanged): A' = A P."""
    out: FloatArray = np.asarray(A, dtype=float) @ P
    return out


def swap_box(lo: Any, hi: Any) -> tuple[FloatArray, FloatArray]:
    """An axis-aligned box: x and y swap, z flips sign so min and max exchange."""
    lo_s, hi_s = swap_points(lo), swap_points(hi)
    return np.minimum(lo_s, hi_s), np.maximum(lo_s, hi_s)


def to_frame(points: Any, frame: str) -> FloatArray:
    """NED points (..., 3) in `frame` ("ned" or "enu")."""
    pts = np.asarray(points, dtype=float)
    return pts if frame == "ned" else swap_points(pts)


def plain(x: float, nd: int = 3) -> float:
    """A plain, rounded Python float (no -0.0) for a message meant to be read."""
    r = round(float(x), nd)
    return 0.0 if r == 0 else r


def fmt_point(point: Any, frame: str = "ned") -> str:
    """`[x, y, z]` of a NED point, in `frame`, with plain numbers."""
    return "[" + ", ".join(f"{plain(v):g}" for v in to_frame(point, frame)) + "]"


def fmt_box(lo: Any, hi: Any, frame: str = "ned") -> str:
    """An axis-aligned NED box, in `frame`, as `[min]..[max]` with plain numbers."""
    a, b = (lo, hi) if frame == "ned" else swap_box(lo, hi)
    return f"{fmt_point(a)}..{fmt_point(b)}"


def _swap_bound(value: Any) -> Any:
    """A scenario bound B: number | [lo, hi] | [[lo,hi]] * 3 (per axis) | the vehicle form
    {"horizontal", "up", "down" | "vertical", "box": B} (up, down and the norm are physical: only
    its box turns)."""
    if isinstance(value, dict):
        return {k: _swap_bound(v) if k == "box" else v for k, v in value.items()}
    if isinstance(value, int | float):
        return value
    if len(value) == 2 and all(isinstance(v, int | float) for v in value):
        return value  # the same interval on every axis
    x, y, z = value
    return [list(y), list(x), [-z[1], -z[0]]]


def _swap_region(region: dict[str, Any]) -> dict[str, Any]:
    out = dict(region)
    if "A" in region:
        out["A"] = swap_halfspaces(region["A"]).tolist()
    if "vertices" in region:
        out["vertices"] = swap_points(region["vertices"]).tolist()
    return out


def scenario_to_ned(obj: dict[str, Any]) -> dict[str, Any]:
    """A scenario dict (common.md format, already schema-checked) in NED."""
    if obj.get("frame", "ned") == "ned":
        return dict(obj)
    out = dict(obj)
    out["frame"] = "ned"
    out["waypoints"] = swap_points(obj["waypoints"]).tolist()
    if "bounds" in obj:
        out["bounds"] = {k: _swap_bound(v) for k, v in obj["bounds"].items()}
    for key in ("corridors", "obstacles"):
        if key in obj:
            out[key] = [_swap_region(r) for r in obj[key]]
    if "map" in obj:
        lo, hi = swap_box(obj["map"]["min"], obj["map"]["max"])
        out["map"] = {"min": lo.tolist(), "max": hi.tolist()}
    for key in ("initial", "final"):
        if key in obj:
            out[key] = {k: swap_points(v).tolist() for k, v in obj[key].items()}
    return out


def obstacles_to_ned(obj: dict[str, Any]) -> dict[str, Any]:
    """An `obstacles` message in NED."""
    if obj.get("frame", "ned") == "ned":
        return dict(obj)
    out = dict(obj)
    out["frame"] = "ned"
    out["add"] = [_swap_region(r) for r in obj.get("add", [])]
    return out


def change_to_ned(obj: dict[str, Any]) -> dict[str, Any]:
    """A `change` message in NED (positions only; indices and durations are frame-free)."""
    if obj.get("frame", "ned") == "ned":
        return dict(obj)
    out: dict[str, Any] = {"frame": "ned"}
    for kind, body in obj.items():
        if kind == "frame":
            continue
        if not isinstance(body, dict):  # "origin"
            out[kind] = body
            continue
        body = dict(body)
        if "position" in body:
            body["position"] = swap_points(body["position"]).tolist()
        if "waypoints" in body:
            body["waypoints"] = swap_points(body["waypoints"]).tolist()
        out[kind] = body
    return out
