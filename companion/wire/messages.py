"""Inbound Zenoh payloads -> validated, typed NED messages; the only place a wire error is raised.

Size, JSON, JSON Schema, semantic checks (companion.wire.decode: bytes -> a validated dict),
then one conversion to NED and to typed values (`MissionSpec`, `ObstacleUpdate`, a `Change`,
`Command`). A bad message raises
`MessageError` naming the field (a JSON path such as `waypoints[3][1]`, in the message's own
indices) and the reason, with positions in the frame the operator used; `read` returns it
instead of raising, so the caller turns it into a `rejected` event and the flight goes on.
"""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass
from dataclasses import field as dc_field
from typing import Any

import numpy as np

from companion.config import Config, LimitsConfig, tracking_allowance
from companion.geodesy import Placement
from companion.wire.decode import check_durations, check_geofence, check_point, decode, validator
from companion.wire.errors import (
    InternalError,
    MessageError,
    Oversized,
    quote,
)
from companion.wire.frames import (
    change_to_ned,
    fmt_point,
    obstacles_to_ned,
    plain,
    scenario_to_ned,
)
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


def warm_validators() -> None:
    """Build (and check) every schema validator once: the first build takes ~0.1 s."""
    for kind in KINDS:
        validator(kind)
    # and the hull's first use (it imports scipy.spatial: ~0.1 s) happens now, not in flight
    cube = [[x, y, z] for x in (0, 1) for y in (0, 1) for z in (0, 1)]
    parse_region({"vertices": cube}, "warm-up")


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
    radius: float  # obstacles are inflated by this: the vehicle's radius + the tracking allowance in use
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


def mission_from_message(obj: dict[str, Any], cfg: Config, frame: str = "ned",
                         autopilot: str | None = None) -> MissionSpec:
    """A schema-valid mission dict, already in NED, to a MissionSpec (or MessageError).
    `autopilot`: whose tracking allowance `[planner] tracking_allowance = "autopilot"` means."""
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
    allowance = tracking_allowance(cfg.planner, autopilot)[0]
    radius = max(cfg.planner.vehicle_radius, float(obj.get("vehicle_radius", 0.0))) + allowance
    bounds = bounds_from(obj.get("bounds"), cfg)
    if durations is not None:
        speed = np.minimum(-bounds.lo[0], bounds.hi[0])
        check_durations(durations, "durations" if "durations" in obj else "times", cfg.limits, wps, speed,
                        first=0 if "durations" in obj else 1)
    return MissionSpec(
        id=str(obj["id"]), waypoints=wps, durations=durations, bounds=bounds,
        obstacles=obstacles, map_lo=map_lo, map_hi=map_hi, radius=radius, start=start,
        autostart=bool(obj.get("autostart", True)), initial=initial, frame=frame, raw=obj,
        allowance=allowance,
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


NOT_READY = ("the autopilot is not ready: its position estimate has not settled (it reports HOME_POSITION at its "
             "local origin, as PX4 does until its estimator is ready, ~37 s after boot; until then PX4 SIH's "
             "estimate on the ground drifted 23-42 m and was then reset), so a plan from the position it reports "
             "would start tens of metres from the vehicle, and the geofence cannot follow home; send the mission "
             "again once status `home` is set")


def read(kind: str, payload: bytes | Oversized, cfg: Config, home: FloatArray | None = None, *,
         home_pending: bool = False, fleet: Placement | str | None = None,
         autopilot: str | None = None) -> Message | MessageError:
    """Bytes -> a typed NED message in the autopilot's local frame, or the MessageError that
    says why not. `home`: HOME_POSITION's local position, for messages with `"origin":
    "home"`; `fleet`: where the local frame sits in the fleet frame, for `"origin": "fleet"`
    (companion.fleet.FleetFrame.for_messages); `autopilot`: the one linked ("px4", "ardupilot"),
    whose tracking allowance a mission's obstacles are inflated by when `[planner]
    tracking_allowance` is "autopilot". Never raises: anything unforeseen comes back as an `InternalError` (a rejection
    the service also reports as an `error` event)."""
    try:
        obj = decode(kind, payload, limits=cfg.limits)
        frame = str(obj.get("frame", "ned"))
        if kind == "mission" and home_pending:
            # whatever the frame: the plan starts from the reported position, which is not the vehicle's
            return MessageError("", NOT_READY)
        cfg = fence_at_home(cfg, home)
        try:
            if kind == "mission":
                return mission_from_message(to_local(kind, scenario_to_ned(obj), home, fleet), cfg, frame, autopilot)
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
