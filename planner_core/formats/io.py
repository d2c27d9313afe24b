"""Scenario and trajectory JSON (formats fixed in notes/common.md).

`load_scenario` validates everything and raises `ScenarioError` naming the
field and index ("bounds.velocity[1]: lo 3 > hi 2"). When a scenario has no
times/durations, the problem's times come from `planner_core.timing.allocate_times`
(a start for the planner; `Scenario.durations_given` says they were not the user's);
when it has obstacles but no corridors, corridors come from
`planner_core.geometry.build_corridors` (both imported lazily; a blocked
segment raises that module's `CorridorError`, which is not an input error).

Bounds: each order is a per-axis form (`_bound`) or the vehicle form {"horizontal", "up",
"down" | "vertical", "box"} (`vehicle_bound`: a horizontal norm bound, vertical limits up and
down in the scenario's frame); "polygon_sides" sets the norm's certifying polygon; the writer is
`bounds_to_dict` (docs/bounds.md).

Timing keys (what the planner CLI does with them; `planner_core.missions.plan_mission`):
- "timing": "auto" (the default): the given times/durations, or when there are none the
  fastest durations the bounds and corridors allow (`allocation.fastest_durations`);
  "fastest": the fastest durations even when times are given; "default": the given
  times, or `allocate_times` when there are none (the slower allocation that was the
  default before).
- "time_weight": rho > 0: the durations minimising J + rho T (overrides "timing").

Trajectory JSON (`trajectory_to_dict` / `trajectory_from_dict`): "format", "frame",
"degree", "segments" (each "t0", "t1", "control_points", "corridor") and "stats", plus
"waypoint_index" when the writer knows it: for each waypoint the user gave, the index of the
trajectory waypoint (segment boundary) it is; the boundaries not listed are knots (the
fastest allocation's splits of long legs, a replan's split at from_time). `replan` counts a
change's indices in the user's waypoints through it (`planner_core.indices`); a file without
it counts every boundary as a waypoint (`waypoint_index_from_dict` returns None).
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from numpy.typing import NDArray

from planner_core.errors import FieldError
from planner_core.problem import (
    DEGREE,
    POLYGON_SIDES,
    Bounds,
    FloatArray,
    Polytope,
    Problem,
    Trajectory,
    rest_jet,
)

TRAJECTORY_FORMAT = "bezier-trajectory/1"
SCENARIO_KEYS = frozenset({
    "frame", "waypoints", "times", "durations", "bounds", "corridors", "obstacles", "map",
    "vehicle_radius", "initial", "final", "description", "timing", "time_weight",
})
TIMINGS = ("auto", "default", "fastest")  # module docstring; the allocation runs at plan time
BOUND_KEYS = ("velocity", "acceleration", "jerk", "snap")
STATE_KEYS = ("velocity", "acceleration", "jerk", "snap")
WAYPOINT_TOL = 1e-9


class ScenarioError(FieldError):
    """Invalid scenario or trajectory JSON; `.field` names the offending entry."""


@dataclass(frozen=True)
class Scenario:
    problem: Problem
    frame: str
    obstacles: tuple[Polytope, ...]
    map_box: tuple[FloatArray, FloatArray] | None
    vehicle_radius: float
    raw: dict[str, Any] = field(compare=False)
    description: str = ""
    timing: str = "auto"  # one of TIMINGS (module docstring)
    time_weight: float | None = None  # rho > 0: the planner CLI minimises J + rho T over the durations
    durations_given: bool = True  # False: the problem's times are allocate_times', not the user's


# --- small validators ------------------------------------------------------


def _number(x: Any, name: str) -> float:
    if isinstance(x, bool) or not isinstance(x, int | float):
        raise ScenarioError(name, f"expected a number, got {type(x).__name__}")
    v = float(x)
    if not math.isfinite(v):
        raise ScenarioError(name, f"must be finite, got {x}")
    return v


def _vector(x: Any, name: str, n: int = 3) -> FloatArray:
    if not isinstance(x, Sequence) or isinstance(x, str) or len(x) != n:
        raise ScenarioError(name, f"expected a list of {n} numbers")
    return np.array([_number(v, f"{name}[{i}]") for i, v in enumerate(x)])


def _matrix(x: Any, name: str, cols: int = 3, min_rows: int = 1) -> FloatArray:
    if not isinstance(x, Sequence) or isinstance(x, str) or len(x) < min_rows:
        raise ScenarioError(name, f"expected a list of at least {min_rows} rows of {cols} numbers")
    return np.array([_vector(r, f"{name}[{i}]", cols) for i, r in enumerate(x)]).reshape(-1, cols)


def _numbers(x: Any, name: str) -> FloatArray:
    if not isinstance(x, Sequence) or isinstance(x, str):
        raise ScenarioError(name, "expected a list of numbers")
    return np.array([_number(v, f"{name}[{i}]") for i, v in enumerate(x)], dtype=float)


def _keys(obj: Any, name: str, allowed: Sequence[str] | frozenset[str]) -> Mapping[str, Any]:
    if not isinstance(obj, Mapping):
        raise ScenarioError(name, f"expected an object, got {type(obj).__name__}")
    for k in obj:
        if k not in allowed:
            prefix = f"{name}." if name else ""
            raise ScenarioError(f"{prefix}{k}", f"unknown key (allowed: {', '.join(sorted(allowed))})")
    return obj


def _bound(x: Any, name: str) -> tuple[FloatArray, FloatArray]:
    """B = number (symmetric) | [lo, hi] | [[lo, hi] x 3]."""
    if isinstance(x, int | float) and not isinstance(x, bool):
        v = _number(x, name)
        if v <= 0:
            raise ScenarioError(name, f"symmetric bound must be > 0, got {v}")
        return np.full(3, -v), np.full(3, v)
    if isinstance(x, Sequence) and not isinstance(x, str) and len(x) == 2 and all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in x
    ):
        lo, hi = _number(x[0], f"{name}[0]"), _number(x[1], f"{name}[1]")
        if lo > hi:
            raise ScenarioError(name, f"lo {lo:g} > hi {hi:g}")
        return np.full(3, lo), np.full(3, hi)
    if isinstance(x, Sequence) and not isinstance(x, str) and len(x) == 3:
        lo_a, hi_a = np.zeros(3), np.zeros(3)
        for i, pair in enumerate(x):
            p = _vector(pair, f"{name}[{i}]", 2)
            if p[0] > p[1]:
                raise ScenarioError(f"{name}[{i}]", f"lo {p[0]:g} > hi {p[1]:g}")
            lo_a[i], hi_a[i] = p
        return lo_a, hi_a
    raise ScenarioError(name, "expected a number, [lo, hi] or [[lo, hi], [lo, hi], [lo, hi]]")


NORM_KEYS = ("horizontal", "up", "down", "vertical", "box")


def _positive(x: Any, name: str) -> float:
    v = _number(x, name)
    if v <= 0:
        raise ScenarioError(name, f"must be > 0, got {v:g}")
    return v


def vehicle_bound(obj: Any, name: str, z_up: bool) -> tuple[FloatArray, FloatArray, float]:
    """One order's bound in the vehicle form (docs/bounds.md):
    {"horizontal": h, "up": u, "down": d} (or "vertical": v for both senses), optionally with
    "box": any per-axis form (both apply). h bounds the norm of the (x, y) part; up and down
    are magnitudes along the vertical, +z when `z_up` (ENU), -z otherwise (NED). Every axis must
    be bounded: x and y by "horizontal" or "box", z by "up" and "down", "vertical" or "box".
    Returns the per-axis lo, hi (3,) and the norm bound (inf: none)."""
    raw = _keys(obj, name, NORM_KEYS)
    lo, hi = np.full(3, -np.inf), np.full(3, np.inf)
    if "box" in raw:
        lo, hi = _bound(raw["box"], f"{name}.box")
    h = _positive(raw["horizontal"], f"{name}.horizontal") if "horizontal" in raw else np.inf
    if "vertical" in raw and ("up" in raw or "down" in raw):
        raise ScenarioError(f"{name}.vertical", "give either 'vertical' or 'up' and 'down', not both")
    if ("up" in raw) != ("down" in raw):
        missing = "down" if "up" in raw else "up"
        raise ScenarioError(f"{name}.{missing}", "missing ('up' and 'down' come together; 'vertical' for both)")
    if "vertical" in raw:
        up = down = _positive(raw["vertical"], f"{name}.vertical")
    elif "up" in raw:
        up, down = _positive(raw["up"], f"{name}.up"), _positive(raw["down"], f"{name}.down")
    else:
        up = down = np.inf
    z_lo, z_hi = (-down, up) if z_up else (-up, down)
    lo[2], hi[2] = max(lo[2], z_lo), min(hi[2], z_hi)
    if lo[2] > hi[2]:
        raise ScenarioError(name, f"the vertical limits and the box leave z no room ([{lo[2]:g}, {hi[2]:g}])")
    if not np.isfinite(h) and not (np.all(np.isfinite(lo[:2])) and np.all(np.isfinite(hi[:2]))):
        raise ScenarioError(f"{name}.horizontal", "missing (x and y need 'horizontal' or a 'box')")
    if not (np.isfinite(lo[2]) and np.isfinite(hi[2])):
        raise ScenarioError(f"{name}.up", "missing (z needs 'up' and 'down', 'vertical' or a 'box')")
    return lo, hi, h


def bounds_to_dict(bounds: Bounds, frame: str = "enu") -> dict[str, Any]:
    """The scenario file's "bounds" for `bounds` (what `load_scenario` reads back to the same
    limits): per order the per-axis form, or the vehicle form where there is a norm bound
    ("up"/"down" in `frame`; a "box" where x or y also has finite per-axis limits). Orders
    without any bound are left out. ValueError for limits the file cannot say (a norm bound with
    partly infinite per-axis limits besides z)."""
    if frame not in ("enu", "ned"):
        raise ValueError(f"frame: expected 'enu' or 'ned', got {frame!r}")
    out: dict[str, Any] = {}
    for k, key in enumerate(BOUND_KEYS):
        lo, hi, h = bounds.lo[k], bounds.hi[k], float(bounds.horizontal[k])
        finite = np.isfinite(lo) & np.isfinite(hi)
        per_axis = [[float(a), float(b)] for a, b in zip(lo, hi, strict=True)]
        if not np.isfinite(h):
            if np.all(finite):
                out[key] = per_axis
            elif np.any(np.isfinite(lo)) or np.any(np.isfinite(hi)):
                raise ValueError(f"bounds.{key}: per-axis limits must be all finite or all infinite")
            continue
        if np.all(finite):
            out[key] = {"horizontal": h, "box": per_axis}
        elif not np.any(np.isfinite(lo[:2]) | np.isfinite(hi[:2])) and finite[2] and lo[2] < 0.0 < hi[2]:
            up, down = (float(hi[2]), float(-lo[2])) if frame == "enu" else (float(-lo[2]), float(hi[2]))
            out[key] = {"horizontal": h, "up": up, "down": down}
        else:
            raise ValueError(f"bounds.{key}: a norm bound with these per-axis limits has no file form")
    if bounds.sides != POLYGON_SIDES:
        out["polygon_sides"] = bounds.sides
    return out


def _polytope(obj: Any, name: str, allow_vertices: bool) -> Polytope:
    keys = ("A", "b", "vertices") if allow_vertices else ("A", "b")
    _keys(obj, name, keys)
    if "vertices" in obj:
        if "A" in obj or "b" in obj:
            raise ScenarioError(name, "give either {A, b} or {vertices}, not both")
        verts = _matrix(obj["vertices"], f"{name}.vertices", 3, 4)
        try:
            from planner_core.geometry import polytope_from_vertices
        except ImportError:
            return _hull_polytope(verts, name)
        try:
            return polytope_from_vertices(verts)
        except ValueError as e:
            raise ScenarioError(f"{name}.vertices", str(e)) from e
    if "A" not in obj or "b" not in obj:
        raise ScenarioError(name, "needs both 'A' and 'b'")
    A = _matrix(obj["A"], f"{name}.A", 3, 1)
    b = _numbers(obj["b"], f"{name}.b")
    if b.shape[0] != A.shape[0]:
        raise ScenarioError(f"{name}.b", f"has {b.shape[0]} entries, A has {A.shape[0]} rows")
    norms = np.linalg.norm(A, axis=1)
    if np.any(norms == 0):
        raise ScenarioError(f"{name}.A[{int(np.argmin(norms))}]", "zero row")
    return Polytope(A, b)


def _hull_polytope(verts: FloatArray, name: str) -> Polytope:
    from scipy.spatial import ConvexHull, QhullError

    try:
        hull = ConvexHull(verts)
    except QhullError as e:
        raise ScenarioError(f"{name}.vertices", "degenerate (no 3-D volume)") from e
    eq = hull.equations
    return Polytope(np.ascontiguousarray(eq[:, :3]), np.ascontiguousarray(-eq[:, 3]))


def _state(obj: Any, name: str, position: FloatArray) -> FloatArray:
    _keys(obj, name, STATE_KEYS)
    jet = rest_jet(position)
    for k, key in enumerate(STATE_KEYS, start=1):
        if key in obj:
            jet[k] = _vector(obj[key], f"{name}.{key}")
    return jet


def load_scenario(obj: Any) -> Scenario:
    """Validate a scenario dict and build its Problem (see module docstring)."""
    raw = _keys(obj, "", SCENARIO_KEYS)
    frame = raw.get("frame", "enu")
    if frame not in ("enu", "ned"):
        raise ScenarioError("frame", f"expected 'enu' or 'ned', got {frame!r}")
    description = raw.get("description", "")
    if not isinstance(description, str):
        raise ScenarioError("description", "expected a string")
    if "waypoints" not in raw:
        raise ScenarioError("waypoints", "missing")
    wps = _matrix(raw["waypoints"], "waypoints", 3, 2)
    bounds = _bounds(raw, str(frame))
    init = _state(raw.get("initial", {}), "initial", wps[0])
    fin = _state(raw.get("final", {}), "final", wps[-1])
    radius = _number(raw.get("vehicle_radius", 0.0), "vehicle_radius")
    if radius < 0:
        raise ScenarioError("vehicle_radius", f"must be >= 0, got {radius}")
    map_box = _map(raw)
    obstacles = tuple(
        _polytope(o, f"obstacles[{i}]", True) for i, o in enumerate(_list(raw.get("obstacles", []), "obstacles"))
    )
    times = _times(raw, wps, bounds, init)
    corridors = _corridors(raw, wps, obstacles, map_box, radius)
    problem = Problem(wps, times, bounds, init, fin, corridors)
    timing = raw.get("timing", "auto")
    if not isinstance(timing, str) or timing not in TIMINGS:
        raise ScenarioError("timing", f"expected one of {', '.join(repr(t) for t in TIMINGS)}, got {timing!r}")
    rho = None
    if "time_weight" in raw:
        rho = _number(raw["time_weight"], "time_weight")
        if rho <= 0.0:
            raise ScenarioError("time_weight", f"must be > 0 (seconds of flight are worth rho units of cost), got {rho}")
    given = "times" in raw or "durations" in raw
    return Scenario(problem, str(frame), obstacles, map_box, radius, dict(raw), description, timing, rho, given)


def _list(x: Any, name: str) -> Sequence[Any]:
    if not isinstance(x, Sequence) or isinstance(x, str):
        raise ScenarioError(name, "expected a list")
    return x


def _bounds(raw: Mapping[str, Any], frame: str = "enu") -> Bounds:
    if "bounds" not in raw:
        raise ScenarioError("bounds", "missing")
    bobj = _keys(raw["bounds"], "bounds", (*BOUND_KEYS, "polygon_sides"))
    return parse_bounds(bobj, "bounds", z_up=frame == "enu")


def parse_bounds(bobj: Mapping[str, Any], name: str, z_up: bool, *, required: Sequence[str] = BOUND_KEYS[:2],
                 base: Bounds | None = None) -> Bounds:
    """The "bounds" object (keys `BOUND_KEYS`, optional "polygon_sides"): per order a per-axis
    form (`_bound`) or the vehicle form (`vehicle_bound`). Orders not given come from `base`
    (unbounded without one); `required` orders must be given."""
    lo = np.full((4, 3), -np.inf) if base is None else np.array(base.lo, dtype=float)
    hi = np.full((4, 3), np.inf) if base is None else np.array(base.hi, dtype=float)
    hor = np.full(4, np.inf) if base is None else np.array(base.horizontal, dtype=float)
    for k, key in enumerate(BOUND_KEYS):
        if key not in bobj:
            continue
        if isinstance(bobj[key], Mapping):
            lo[k], hi[k], hor[k] = vehicle_bound(bobj[key], f"{name}.{key}", z_up)
        else:
            lo[k], hi[k] = _bound(bobj[key], f"{name}.{key}")
            hor[k] = np.inf
    for key in required:
        if key not in bobj:
            raise ScenarioError(f"{name}.{key}", "missing (velocity and acceleration bounds are required)")
    sides = POLYGON_SIDES if base is None else base.sides
    if "polygon_sides" in bobj:
        n = bobj["polygon_sides"]
        if isinstance(n, bool) or not isinstance(n, int) or n < 4 or n % 2 or n > 1024:
            raise ScenarioError(f"{name}.polygon_sides", f"expected an even integer in 4..1024, got {n!r}")
        sides = n
    return Bounds(lo, hi, horizontal=hor, sides=sides)


def _map(raw: Mapping[str, Any]) -> tuple[FloatArray, FloatArray] | None:
    if "map" not in raw:
        return None
    mobj = _keys(raw["map"], "map", ("min", "max"))
    if "min" not in mobj or "max" not in mobj:
        raise ScenarioError("map", "needs both 'min' and 'max'")
    lo, hi = _vector(mobj["min"], "map.min"), _vector(mobj["max"], "map.max")
    for a in range(3):
        if lo[a] >= hi[a]:
            raise ScenarioError(f"map.min[{a}]", f"{lo[a]:g} >= map.max[{a}] {hi[a]:g}")
    return lo, hi


def _times(raw: Mapping[str, Any], wps: FloatArray, bounds: Bounds, init: FloatArray) -> FloatArray:
    m = wps.shape[0]
    if "times" in raw and "durations" in raw:
        raise ScenarioError("times", "give either 'times' or 'durations', not both")
    if "times" in raw:
        t = _numbers(raw["times"], "times")
        if t.shape[0] != m:
            raise ScenarioError("times", f"has {t.shape[0]} entries for {m} waypoints")
        for i in range(1, m):
            if t[i] <= t[i - 1]:
                raise ScenarioError(f"times[{i}]", f"{t[i]:g} is not after times[{i - 1}] {t[i - 1]:g}")
        return t
    if "durations" in raw:
        d = _numbers(raw["durations"], "durations")
        if d.shape[0] != m - 1:
            raise ScenarioError("durations", f"has {d.shape[0]} entries for {m - 1} segments")
        for i, v in enumerate(d):
            if v <= 0:
                raise ScenarioError(f"durations[{i}]", f"must be > 0, got {v:g}")
        return np.concatenate([[0.0], np.cumsum(d)])
    try:
        from planner_core.timing import allocate_times
    except ImportError as e:
        raise ScenarioError("times", "missing, and automatic time allocation is unavailable") from e
    return np.asarray(allocate_times(wps, bounds, t0=0.0, initial_velocity=init[1]), dtype=float)


def _corridors(
    raw: Mapping[str, Any],
    wps: FloatArray,
    obstacles: tuple[Polytope, ...],
    map_box: tuple[FloatArray, FloatArray] | None,
    radius: float,
) -> tuple[Polytope | None, ...] | None:
    m = wps.shape[0]
    if "corridors" in raw:
        items = _list(raw["corridors"], "corridors")
        if len(items) != m - 1:
            raise ScenarioError("corridors", f"has {len(items)} entries for {m - 1} segments")
        polys = tuple(None if c is None else _polytope(c, f"corridors[{i}]", False) for i, c in enumerate(items))
        for i, poly in enumerate(polys):
            if poly is None:
                continue
            for w in (i, i + 1):
                v = poly.violation(wps[w])
                if v > WAYPOINT_TOL:
                    raise ScenarioError(f"waypoints[{w}]", f"outside corridors[{i}] by {v:.3g}")
        return polys
    if not obstacles:
        return None
    from planner_core.geometry import build_corridors

    return tuple(build_corridors(wps, obstacles, map_box, radius))


# --- trajectories ------------------------------------------------------------


def _poly_dict(p: Polytope | None) -> dict[str, Any] | None:
    if p is None:
        return None
    return {"A": p.A.tolist(), "b": p.b.tolist()}


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return _jsonable(x.tolist())
    if isinstance(x, np.generic):
        return _jsonable(x.item())
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, str | int | float | bool) or x is None:
        return x
    to_dict = getattr(x, "to_dict", None)  # e.g. a SeparationCertificate in a plan's stats
    if callable(to_dict):
        return _jsonable(to_dict())
    return str(x)


def trajectory_to_dict(
    traj: Trajectory, frame: str = "enu", waypoint_index: Sequence[int] | NDArray[np.int64] | None = None
) -> dict[str, Any]:
    """The JSON form; `waypoint_index`: the user waypoints' boundary indices (module docstring)."""
    corridors = traj.corridors or (None,) * traj.n_segments
    out: dict[str, Any] = {
        "format": TRAJECTORY_FORMAT,
        "frame": frame,
        "degree": DEGREE,
        "segments": [
            {
                "t0": float(traj.times[s]),
                "t1": float(traj.times[s + 1]),
                "control_points": traj.control_points[s].tolist(),
                "corridor": _poly_dict(corridors[s]),
            }
            for s in range(traj.n_segments)
        ],
        "stats": _jsonable(traj.stats),
    }
    if waypoint_index is not None:
        from planner_core.indices import WaypointMap

        try:
            wm = WaypointMap.checked(np.asarray(waypoint_index), traj.n_segments + 1)
        except FieldError as e:  # a bug of the caller's, not bad input
            raise ValueError(f"trajectory_to_dict: {e}") from e
        out["waypoint_index"] = wm.index.tolist()
    return out


def trajectory_json(
    traj: Trajectory, frame: str = "enu", waypoint_index: Sequence[int] | NDArray[np.int64] | None = None
) -> str:
    """`trajectory_to_dict` as JSON text, one segment (and the waypoint index) per line.

    The same JSON value as `json.dumps(trajectory_to_dict(...), indent=1)` (what the CLI wrote
    before; `json.loads` of either gives equal dicts, every float by the same `repr`), about 20x
    faster on a 1000-segment plan: json's indenting encoder is pure Python, a float at a time,
    while a line here is one call of its C encoder; and a file of one line per segment reads
    and diffs better than one of a number per line."""
    import json

    d = trajectory_to_dict(traj, frame, waypoint_index)
    lines = ["{"]
    items = list(d.items())
    for n, (key, value) in enumerate(items):
        head = f" {json.dumps(key)}: "
        comma = "," if n < len(items) - 1 else ""
        if key == "segments":
            body = ",\n  ".join(json.dumps(seg) for seg in value)
            lines.append(f"{head}[\n  {body}\n ]{comma}" if value else f"{head}[]{comma}")
        elif key == "stats":
            lines.append(head + json.dumps(value, indent=1).replace("\n", "\n ") + comma)
        else:
            lines.append(head + json.dumps(value) + comma)
    lines.append("}")
    return "\n".join(lines)


TRAJECTORY_KEYS = ("format", "frame", "degree", "segments", "stats", "waypoint_index")


def waypoint_index_from_dict(d: Any) -> NDArray[np.int64] | None:
    """The "waypoint_index" of a trajectory dict, checked against its segments (None: absent)."""
    obj = _keys(d, "", TRAJECTORY_KEYS)
    raw = obj.get("waypoint_index")
    if raw is None:
        return None
    segs = _list(obj.get("segments"), "segments")
    if not isinstance(raw, list) or not all(isinstance(v, int) and not isinstance(v, bool) for v in raw):
        raise ScenarioError("waypoint_index", "expected a list of integer indices")
    from planner_core.indices import WaypointMap

    try:
        return WaypointMap.checked(np.asarray(raw, dtype=np.int64), len(segs) + 1).index
    except FieldError as e:
        raise ScenarioError(e.field, e.reason) from e


def trajectory_from_dict(d: Any) -> Trajectory:
    obj = _keys(d, "", TRAJECTORY_KEYS)
    if obj.get("format") != TRAJECTORY_FORMAT:
        raise ScenarioError("format", f"expected {TRAJECTORY_FORMAT!r}, got {obj.get('format')!r}")
    if obj.get("degree", DEGREE) != DEGREE:
        raise ScenarioError("degree", f"expected {DEGREE}")
    segs = _list(obj.get("segments"), "segments")
    if not segs:
        raise ScenarioError("segments", "empty")
    times: list[float] = []
    ctrl: list[FloatArray] = []
    corridors: list[Polytope | None] = []
    for i, s in enumerate(segs):
        so = _keys(s, f"segments[{i}]", ("t0", "t1", "control_points", "corridor"))
        t0, t1 = _number(so.get("t0"), f"segments[{i}].t0"), _number(so.get("t1"), f"segments[{i}].t1")
        if t1 <= t0:
            raise ScenarioError(f"segments[{i}].t1", f"{t1:g} <= t0 {t0:g}")
        if i and abs(t0 - times[-1]) > 1e-12 * (1 + abs(t0)):
            raise ScenarioError(f"segments[{i}].t0", f"{t0:g} != previous t1 {times[-1]:g}")
        if i == 0:
            times.append(t0)
        times.append(t1)
        cp = _matrix(so.get("control_points"), f"segments[{i}].control_points", 3, DEGREE + 1)
        if cp.shape[0] != DEGREE + 1:
            raise ScenarioError(f"segments[{i}].control_points", f"expected {DEGREE + 1} points")
        ctrl.append(cp)
        c = so.get("corridor")
        corridors.append(None if c is None else _polytope(c, f"segments[{i}].corridor", False))
    cors = None if all(c is None for c in corridors) else tuple(corridors)
    stats = obj.get("stats", {})
    return Trajectory(np.array(times), np.stack(ctrl), cors, dict(stats) if isinstance(stats, dict) else {})


__all__ = [
    "Scenario",
    "ScenarioError",
    "load_scenario",
    "trajectory_from_dict",
    "trajectory_json",
    "trajectory_to_dict",
    "waypoint_index_from_dict",
]
