"""PX4's events as the mock's PX4 flavour emits and describes them (no import from the companion).

Ids are PX4's `events::ID(name)`: the 24-bit FNV-1a hash of the name with the component (1, the
autopilot) in the top byte (PX4 src/lib/events, libevents). `all_events()` is the events
metadata in the format of PX4's build output `all_events.json` (served by PX4 over MAVLink FTP
as /etc/extras/all_events.json.xz): per component, the enums and the event groups, each event
keyed by its 24-bit sub-id with its name, message template and argument types. The messages
and argument types are PX4's own (sources named beside each event); "mock_" events are the
mock's, for refusals PX4 words differently.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from typing import Any

# The events protocol's log levels (MAVLink EVENT log_levels nibbles; 0-7 as MAV_SEVERITY).
LEVELS = ("EMERGENCY", "ALERT", "CRITICAL", "ERROR", "WARNING", "NOTICE", "INFO", "DEBUG", "PROTOCOL", "DISABLED")
LEVEL = {name: i for i, name in enumerate(LEVELS)}


def event_id(name: str, component: int = 1) -> int:
    """PX4's events::ID(name): FNV-1a 32 of the name, low 24 bits, component in the top byte."""
    h = 0x811C9DC5
    for byte in name.encode("ascii"):
        h = ((h ^ byte) * 0x01000193) & 0xFFFFFFFF
    return (h & 0xFFFFFF) | (component << 24)


def log_levels(external: int, internal: int | None = None) -> int:
    """The EVENT log_levels byte: external level in the low nibble, internal in the high one."""
    inner = external if internal is None else internal
    if not (0 <= external <= 15 and 0 <= inner <= 15):
        raise ValueError(f"log level out of range: external {external}, internal {inner}")
    return (inner << 4) | external


@dataclass(frozen=True)
class EventDef:
    name: str
    message: str
    arguments: tuple[tuple[str, str], ...] = ()  # (type, name) in wire order
    group: str = "default"
    description: str = ""

    @property
    def id(self) -> int:
        return event_id(self.name)


_ARM_CHECK_ARGS = (("px4::enums::navigation_mode_group_t", "modes"),
                   ("px4::enums::health_component_index_t", "health_component_index"))

EVENTS: tuple[EventDef, ...] = (
    # src/modules/commander/Commander.cpp (arm, disarm)
    EventDef("commander_armed_by", "Armed by {1}", (("px4::enums::arm_disarm_reason_t", "reason"),)),
    EventDef("commander_disarmed_by", "Disarmed by {1}", (("px4::enums::arm_disarm_reason_t", "reason"),)),
    EventDef("commander_disarm_denied_not_landed", "Disarming denied: not landed"),
    EventDef("commander_arm_denied_resolve_failures", "Arming denied: Resolve system health failures first"),
    # Commander.cpp printRejectMode
    EventDef("commander_modeswitch_not_avail", "Switching to mode '{2}' is currently not possible",
             (("uint32_t", "mavlink_mode"), ("px4::enums::navigation_mode_t", "nav_state"))),
    # Commander.cpp (land detector updates)
    EventDef("commander_takeoff_detected", "Takeoff detected"),
    EventDef("commander_landing_detected", "Landing detected"),
    # src/modules/commander/failsafe/failsafe.cpp notifyUser
    EventDef("commander_failsafe_enter_generic", "Failsafe activated: switching to {2}",
             (("uint32_t", "mavlink_mode"), ("px4::enums::failsafe_action_t", "action"))),
    # src/modules/navigator/takeoff.cpp
    EventDef("navigator_takeoff_default_alt", "Using default takeoff altitude: {1:.1m}", (("float", "altitude"),)),
    # HealthAndArmingChecks/checks/rcAndDataLinkCheck.cpp
    EventDef("check_rc_dl_no_dllink", "No connection to the ground control station", _ARM_CHECK_ARGS,
             "arming_check"),
    # HealthAndArmingChecks/checks/estimatorCheck.cpp (pre-flight innovation checks)
    EventDef("check_estimator_hor_vel_not_stable", "Horizontal velocity unstable", _ARM_CHECK_ARGS, "arming_check"),
    EventDef("check_estimator_vert_vel_not_stable", "Vertical velocity unstable", _ARM_CHECK_ARGS, "arming_check"),
    # HealthAndArmingChecks/checks/modeCheck.cpp
    EventDef("check_modes_local_pos", "Navigation error: No valid position estimate", _ARM_CHECK_ARGS,
             "arming_check",
             "The available positioning data is not sufficient to execute the selected mode."),
    EventDef("check_modes_global_pos", "Navigation error: No valid global position estimate", _ARM_CHECK_ARGS,
             "arming_check"),
    # HealthAndArmingChecks/Common.cpp Report::report
    EventDef("commander_arming_check_summary", "Arming check summary event",
             (("uint8_t", "chunk_idx"), ("px4::enums::health_component_t", "error"),
              ("px4::enums::health_component_t", "warning"),
              ("px4::enums::navigation_mode_group_t", "can_arm_and_run")), "arming_check"),
    EventDef("commander_health_summary", "Health report summary event",
             (("uint8_t", "chunk_idx"), ("px4::enums::health_component_t", "is_present"),
              ("px4::enums::health_component_t", "error"), ("px4::enums::health_component_t", "warning")),
             "health"),
    # The mock's own (PX4 reports these cases with other checks or in its console only).
    EventDef("check_modes_offboard_no_signal", "No offboard signal"),
    EventDef("mock_arm_denied_mode", "Arming denied: the mode does not allow arming"),
    EventDef("mock_takeoff_denied_alt", "Takeoff denied: altitude at or below home"),
)
BY_NAME: dict[str, EventDef] = {e.name: e for e in EVENTS}
IDS: dict[str, int] = {e.name: e.id for e in EVENTS}

# PX4 1.15's enums (src/lib/events/enums.json of the 1.15 line; arm_disarm_reason_t still has
# safety_button at 6, removed later, so landing is 7 and failsafe 15).
_ARM_REASONS = ("transition_to_standby", "rc_stick", "rc_switch", "command_internal", "command_external",
                "mission_start", "safety_button", "auto_disarm_land", "auto_disarm_preflight", "kill_switch",
                "lockdown", "failure_detector", "shutdown", "unit_test", "rc_button", "failsafe")
_ARM_REASON_TEXT = ("Transition to standby", "RC", "RC (switch)", "internal command", "external command",
                    "mission start", "safety button", "landing", "auto preflight disarming", "kill switch",
                    "lockdown", "failure detector", "shutdown request", "unit tests", "RC (button)", "failsafe")
ARM_REASON = {name: i for i, name in enumerate(_ARM_REASONS)}
_HEALTH = ("none", "absolute_pressure", "differential_pressure", "gps", "optical_flow", "vision_position",
           "distance_sensor", "remote_control", "motors_escs", "utm", "logging", "battery", "communication_links",
           "rate_controller", "attitude_controller", "position_controller", "attitude_estimate",
           "local_position_estimate", "mission", "avoidance", "system", "camera", "gimbal", "payload",
           "global_position_estimate", "storage", "parachute", "magnetometer", "accel", "gyro", "open_drone_id")
HEALTH_INDEX = {name: i for i, name in enumerate(_HEALTH)}
HEALTH_BIT = {name: 1 << i for i, name in enumerate(_HEALTH)}
# navigation_mode_group_t: bit = 1 << vehicle_status nav_state (Common.cpp getModeGroup).
NAV_STATE = {"manual": 0, "altctl": 1, "posctl": 2, "mission": 3, "loiter": 4, "rtl": 5, "acro": 10,
             "offboard": 14, "stab": 15, "takeoff": 17, "land": 18}
_NAV_GROUP_TEXT = {"manual": "Fully manual mode (w/o any controller support)", "altctl": "Altitude mode",
                   "posctl": "Position mode", "mission": "Mission mode", "loiter": "Loiter", "rtl": "RTL",
                   "acro": "Acro", "offboard": "Offboard", "stab": "Stabilized", "takeoff": "Takeoff",
                   "land": "Land"}
# navigation_mode_t (the events enum of a single mode, not vehicle_status's nav_state numbers)
_NAV_MODES = ("Manual", "Altitude control", "Position control", "Mission", "Hold", "RTL", "Acro", "Offboard",
              "Stabilized", "Position Slow", "Takeoff", "Land", "Follow Target", "Precision Landing", "Orbit",
              "Vtol Takeoff")
NAV_MODE = {"MANUAL": 0, "ALTCTL": 1, "POSCTL": 2, "MISSION": 3, "LOITER": 4, "RTL": 5, "ACRO": 6, "OFFBOARD": 7,
            "STABILIZED": 8, "TAKEOFF": 10, "LAND": 11}
_FAILSAFE_ACTIONS = ("", "warning", "fallback to position control", "fallback to altitude control",
                     "fallback to stabilized", "hold", "RTL", "land", "descend", "disarm", "terminate")
FAILSAFE_ACTION = {"LOITER": 5, "RTL": 6, "LAND": 7, "disarm": 9, "terminate": 10}


def nav_groups(*names: str) -> int:
    out = 0
    for n in names:
        out |= 1 << NAV_STATE[n]
    return out


def health_bits(*names: str) -> int:
    out = 0
    for n in names:
        out |= HEALTH_BIT[n]
    return out


def arming_check_args(modes: int, component: str) -> bytes:
    """The two arguments PX4 puts before an arming check's own (Report::armingCheckFailure)."""
    return struct.pack("<IB", modes, HEALTH_INDEX[component])


def _enum(type_: str, description: str, entries: dict[int, tuple[str, str]], bitfield: bool = False) -> dict[str, Any]:
    out: dict[str, Any] = {"type": type_, "description": description,
                 "entries": {str(k): {"name": n, "description": d} for k, (n, d) in entries.items()}}
    if bitfield:
        out["is_bitfield"] = True
    return out


def all_events() -> dict[str, Any]:
    """The events metadata, in the layout of PX4's all_events.json (version 2)."""
    enums = {
        "arm_disarm_reason_t": _enum("uint8_t", "Reason for arming/disarming",
                                     {i: (n, _ARM_REASON_TEXT[i]) for i, n in enumerate(_ARM_REASONS)}),
        "health_component_t": _enum("uint32_t", "Bitfield for subsystems & components",
                                    {1 << i: (n, n.replace("_", " ").capitalize()) for i, n in enumerate(_HEALTH)},
                                    bitfield=True),
        "health_component_index_t": _enum("uint8_t", "Index of a subsystem or component (health_component_t bit)",
                                          {i: (n, n.replace("_", " ").capitalize()) for i, n in enumerate(_HEALTH)}),
        "navigation_mode_group_t": _enum("uint32_t", "Navigation/flight mode group bits",
                                         {1 << s: (n, _NAV_GROUP_TEXT[n]) for n, s in NAV_STATE.items()},
                                         bitfield=True),
        "navigation_mode_t": _enum("uint8_t", "Flight mode",
                                   {i: (d.lower().replace(" ", "_"), d) for i, d in enumerate(_NAV_MODES)}),
        "failsafe_action_t": _enum("uint8_t", "failsafe action",
                                   {i: (d.replace(" ", "_") or "none", d) for i, d in enumerate(_FAILSAFE_ACTIONS)}),
    }
    groups: dict[str, dict[str, Any]] = {}
    for e in EVENTS:
        entry: dict[str, Any] = {"name": e.name, "message": e.message}
        if e.description:
            entry["description"] = e.description
        if e.arguments:
            entry["arguments"] = [{"type": t, "name": n} for t, n in e.arguments]
        groups.setdefault(e.group, {"events": {}})["events"][str(e.id & 0xFFFFFF)] = entry
    return {"version": 2, "components": {"1": {"namespace": "px4", "enums": enums, "event_groups": groups,
                                               "supported_protocols": ["events"]}}}
