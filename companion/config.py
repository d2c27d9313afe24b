"""Service configuration: a frozen dataclass tree loaded from TOML.

Every option has a default, so an empty file is a valid configuration. Unknown
keys are rejected with their dotted name because a typo in a safety option
(say `auto_arm`) must not silently fall back to the default.

This module holds the whole (`Config`), the checks of the values, loading and writing the TOML;
each section's dataclass is in companion.config_sections (named here too, for importers).
"""

from __future__ import annotations

import dataclasses
import math
import tomllib
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Any, get_type_hints

from companion.config_sections import (
    TRACKING_ALLOWANCES,
    AutopilotLimitsConfig,
    BoundsConfig,
    FleetConfig,
    GeofenceConfig,
    LimitsConfig,
    LiveConfig,
    MavlinkConfig,
    PlannerConfig,
    RecordingConfig,
    SafetyConfig,
    SetpointConfig,
    VehicleConfig,
    ZenohConfig,
    tracking_allowance,
)

__all__ = [
    "LEAD_MAX",
    "TRACKING_ALLOWANCES",
    "AutopilotLimitsConfig",
    "BoundsConfig",
    "Config",
    "ConfigError",
    "FleetConfig",
    "GeofenceConfig",
    "LimitsConfig",
    "LiveConfig",
    "MavlinkConfig",
    "PlannerConfig",
    "RecordingConfig",
    "SafetyConfig",
    "SetpointConfig",
    "VehicleConfig",
    "ZenohConfig",
    "config_from_dict",
    "config_to_toml",
    "load_config",
    "tracking_allowance",
]


class ConfigError(ValueError):
    """Bad configuration; `key` is the dotted key at fault."""

    def __init__(self, key: str, reason: str) -> None:
        super().__init__(f"{key}: {reason}")
        self.key = key
        self.reason = reason


@dataclass(frozen=True)
class Config:
    vehicle: VehicleConfig = field(default_factory=VehicleConfig)
    zenoh: ZenohConfig = field(default_factory=ZenohConfig)
    mavlink: MavlinkConfig = field(default_factory=MavlinkConfig)
    setpoints: SetpointConfig = field(default_factory=SetpointConfig)
    planner: PlannerConfig = field(default_factory=PlannerConfig)
    geofence: GeofenceConfig = field(default_factory=GeofenceConfig)
    limits: LimitsConfig = field(default_factory=LimitsConfig)
    autopilot_limits: AutopilotLimitsConfig = field(default_factory=AutopilotLimitsConfig)
    safety: SafetyConfig = field(default_factory=SafetyConfig)
    recording: RecordingConfig = field(default_factory=RecordingConfig)
    live: LiveConfig = field(default_factory=LiveConfig)
    fleet: FleetConfig = field(default_factory=FleetConfig)

    def key(self, topic: str) -> str:
        from companion.wire.keys import key

        return key(self.zenoh.prefix, self.vehicle.id, topic)


_CHOICES: dict[str, tuple[str, ...]] = {
    "zenoh.mode": ("peer", "client", "router"),
    "setpoints.yaw_mode": ("hold", "fixed", "velocity"),
    "planner.method": ("iterative", "global"),
    "planner.executor": ("process", "thread"),
    "planner.urgent": ("process", "thread"),
    "planner.timing": ("default", "fastest"),
    "safety.on_exit": ("hold", "land", "rtl"),
    "safety.exit_pilot_mode": ("", "LOITER", "ALT_HOLD", "POSHOLD", "STABILIZE", "POSCTL", "ALTCTL"),
    "geofence.origin": ("home", "local"),
}
_POSITIVE = {
    "mavlink.heartbeat_hz",
    "mavlink.link_timeout",
    "mavlink.command_timeout",
    "setpoints.rate_hz",
    "setpoints.loop_stall_limit",
    "planner.bounds.velocity",
    "planner.bounds.acceleration",
    "planner.bounds.jerk",
    "planner.bounds.snap",
    "planner.split_ahead",
    "planner.search_time",
    "planner.window",
    "planner.workers",
    "limits.max_message_bytes",
    "limits.max_waypoints",
    "limits.max_obstacles",
    "limits.max_obstacle_vertices",
    "limits.max_obstacle_planes",
    "limits.max_obstacle_extent",
    "limits.min_obstacle_width",
    "limits.max_number",
    "limits.max_number_chars",
    "limits.max_string_chars",
    "limits.max_depth",
    "limits.max_obstacles_held",
    "limits.max_pending_missions",
    "limits.max_queued_messages",
    "limits.inbound_rate",
    "limits.inbound_burst",
    "limits.decode_deadline",
    "limits.min_segment_duration",
    "limits.max_segment_duration",
    "safety.takeoff_altitude",
    "safety.arrival_tolerance",
    "setpoints.lead_max",
    "autopilot_limits.headroom",
    "autopilot_limits.timeout",
    "safety.rest_speed",
    "recording.max_bytes",
    "recording.keep_bytes",
    "recording.queue",
}


_NON_NEGATIVE = {"setpoints.accel_lead_tc", "fleet.clock_tolerance", "fleet.separation", "fleet.max_delay", "planner.fallback_delay", "planner.reserve", "autopilot_limits.retries",
                 "safety.tracking_brake", "safety.exit_timeout", "safety.hold_confirm",
                 "safety.hold_altitude_tolerance", "safety.hold_speed_tolerance", "safety.hold_settle", "safety.hold_rest_speed"}

# Keys that were replaced: what to set instead (a safety option must not be dropped silently).
_REPLACED = {
    "safety.max_tracking_error": "replaced by [planner] tracking_allowance (m): the tracking error at which the "
                                 "companion brakes, which now also inflates obstacles (with vehicle_radius), so "
                                 "that the plan's certificate covers the track flown; set that instead "
                                 "(docs/autopilot-limits.md)",
}

LEAD_MAX = 0.5  # s: [setpoints] lead_max's default (PX4 SIH lags ~0.3 s)


def _convert(key: str, hint: Any, value: Any, default: Any) -> Any:
    if key == "setpoints.lead_initial":
        if value == "autopilot":
            return value
        if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= value <= 2.0:
            raise ConfigError(key, f"expected \"autopilot\" or seconds in [0, [setpoints] lead_max], got {value!r}")
        return float(value)
    if key == "planner.tracking_allowance":
        if value == "autopilot":
            return value
        if isinstance(value, bool) or not isinstance(value, int | float) or not (math.isfinite(value) and value >= 0):
            raise ConfigError(key, f"expected \"autopilot\" (the autopilot's own) or metres >= 0, got {value!r}")
        return float(value)
    if key == "setpoints.accel_lead":
        if value == "autopilot":
            return value
        if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= value <= 1.0:
            raise ConfigError(key, f"expected \"autopilot\" or s² in [0, 1], got {value!r}")
        return float(value)
    if key == "setpoints.aim_horizontal":
        if value == "autopilot":
            return value
        want = "\"autopilot\" or a list of at most 4 [k s² in [-10, 10], tc s in [0.1, 10]] pairs"
        if not isinstance(value, list | tuple) or len(value) > 4:
            raise ConfigError(key, f"expected {want}, got {value!r}")
        terms = []
        for i, term in enumerate(value):
            ok = isinstance(term, list | tuple) and len(term) == 2 and all(
                isinstance(x, int | float) and not isinstance(x, bool) and math.isfinite(x) for x in term)
            if not ok or not (-10.0 <= term[0] <= 10.0 and 0.1 <= term[1] <= 10.0):
                raise ConfigError(f"{key}[{i}]", f"expected {want}, got {term!r}")
            terms.append((float(term[0]), float(term[1])))
        return tuple(terms)
    if key == "setpoints.lead":
        if value == "auto":
            return value
        if isinstance(value, bool) or not isinstance(value, int | float) or not 0.0 <= value <= 2.0:
            raise ConfigError(key, f"expected \"auto\" or seconds in [0, [setpoints] lead_max], got {value!r}")
        return float(value)
    if key in ("fleet.origin", "fleet.offset_ned"):
        if not isinstance(value, list) or len(value) not in (0, 3):
            what = "[lat_deg, lon_deg, alt_m]" if key == "fleet.origin" else "[north_m, east_m, down_m]"
            raise ConfigError(key, f"expected {what} (or [] for none), got {value!r}")
        out = tuple(_convert(f"{key}[{i}]", float, v, 0.0) for i, v in enumerate(value))
        if out and key == "fleet.origin":
            from companion.geodesy import check_lla

            try:
                check_lla(out)
            except ValueError as exc:
                raise ConfigError(key, str(exc).split(": ", 1)[-1]) from None
        return out
    if dataclasses.is_dataclass(default):
        if not isinstance(value, dict):
            raise ConfigError(key, f"expected a table, got {type(value).__name__}")
        return _build(type(default), value, key + ".")
    if hint is bool:
        if not isinstance(value, bool):
            raise ConfigError(key, f"expected true/false, got {value!r}")
        return value
    if hint is int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(key, f"expected an integer, got {value!r}")
        return value
    if hint is float:
        if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
            raise ConfigError(key, f"expected a finite number, got {value!r}")
        return float(value)
    if hint is str:
        if not isinstance(value, str):
            raise ConfigError(key, f"expected a string, got {value!r}")
        return value
    if isinstance(default, tuple):
        if not isinstance(value, list):
            raise ConfigError(key, f"expected an array, got {value!r}")
        if default and isinstance(default[0], float):
            if len(value) != len(default):
                raise ConfigError(key, f"expected {len(default)} numbers, got {len(value)}")
            return tuple(_convert(f"{key}[{i}]", float, v, 0.0) for i, v in enumerate(value))
        return tuple(_convert(f"{key}[{i}]", str, v, "") for i, v in enumerate(value))
    raise ConfigError(key, "unsupported option type")  # pragma: no cover


def _build(cls: type, table: dict[str, Any], prefix: str = "") -> Any:
    hints = get_type_hints(cls)
    defaults = cls()
    names = {f.name for f in fields(cls)}
    for k in table:
        if prefix + k in _REPLACED:
            raise ConfigError(prefix + k, _REPLACED[prefix + k])
        if k not in names:
            raise ConfigError(prefix + k, f"unknown key (allowed: {', '.join(sorted(names))})")
    kwargs: dict[str, Any] = {}
    for f in fields(cls):
        if f.name not in table:
            continue
        key = prefix + f.name
        value = _convert(key, hints[f.name], table[f.name], getattr(defaults, f.name))
        if key in _CHOICES and value not in _CHOICES[key]:
            raise ConfigError(key, f"must be one of {', '.join(_CHOICES[key])}, got {value!r}")
        if key in _POSITIVE and value <= 0:
            raise ConfigError(key, f"must be > 0, got {value!r}")
        if key in _NON_NEGATIVE and value < 0:
            raise ConfigError(key, f"must be >= 0, got {value!r}")
        if key == "autopilot_limits.headroom" and value > 1.0:
            raise ConfigError(key, f"must be <= 1 (the share of each autopilot limit plans may use), got {value!r}")
        if key == "planner.reserve" and value >= 0.9:
            raise ConfigError(key, f"must be < 0.9 (the share of each bound left unused), got {value!r}")
        kwargs[f.name] = value
    return cls(**kwargs)


def config_from_dict(table: dict[str, Any]) -> Config:
    cfg: Config = _build(Config, table)
    sp = cfg.setpoints
    if sp.lead != "auto" and float(sp.lead) > sp.lead_max:
        raise ConfigError("setpoints.lead", f"expected \"auto\" or seconds in [0, {sp.lead_max}] ([setpoints] "
                          f"lead_max), got {sp.lead!r}")
    lo, hi = cfg.geofence.min, cfg.geofence.max
    for i in range(3):
        if lo[i] >= hi[i]:
            raise ConfigError(f"geofence.min[{i}]", f"must be below geofence.max[{i}]")
    if cfg.fleet.offset_ned and not cfg.fleet.origin:
        raise ConfigError("fleet.offset_ned", "needs [fleet] origin (the frame the offset is in)")
    if cfg.live.foxglove:
        try:
            parse_address(cfg.live.foxglove)
        except ValueError as exc:
            raise ConfigError("live.foxglove", str(exc).split(": ", 1)[-1]) from None
    return cfg


def load_config(path: str | Path) -> Config:
    try:
        with open(path, "rb") as fh:
            table = tomllib.load(fh)
    except tomllib.TOMLDecodeError as exc:
        raise ConfigError(str(path), f"invalid TOML: {exc}") from exc
    return config_from_dict(table)


def _toml_value(value: Any) -> str:
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(value, tuple):
        return "[" + ", ".join(_toml_value(v) for v in value) + "]"
    raise TypeError(type(value))  # pragma: no cover


def _dump_table(obj: Any, name: str, out: list[str]) -> None:
    scalars = [f for f in fields(obj) if not dataclasses.is_dataclass(getattr(obj, f.name))]
    tables = [f for f in fields(obj) if dataclasses.is_dataclass(getattr(obj, f.name))]
    if name and scalars:
        out.append(f"[{name}]")
    for f in scalars:
        out.append(f"{f.name} = {_toml_value(getattr(obj, f.name))}")
    if name and scalars:
        out.append("")
    for f in tables:
        _dump_table(getattr(obj, f.name), f"{name}.{f.name}" if name else f.name, out)


def config_to_toml(cfg: Config | None = None) -> str:
    out: list[str] = []
    _dump_table(cfg or Config(), "", out)
    return "\n".join(out).rstrip() + "\n"


def parse_address(text: str) -> tuple[str, int]:
    """"HOST:PORT", "[v6]:PORT" or ":PORT" (loopback); port 0: any free port. ValueError
    with the reason."""
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not 0 <= int(port) < 65536:
        raise ValueError(f"[live] foxglove = {text!r}: expected HOST:PORT, e.g. 127.0.0.1:8765")
    return (host.strip("[]") or "127.0.0.1"), int(port)
