"""The recording's channels: names, schemas, frames, and the records written on them.

Every channel has a schema a viewer understands. JSON channels carry a JSON Schema
(`jsonschema` encoding); the 3D channels carry Foxglove's own message types as the Foxglove
SDK encodes them (protobuf, with the SDK's schema), which Foxglove shows in its 3D panel.

Frames (docs/recording.md):
- `local_ned`: the autopilot's local frame, as everything inside the service (x north, y east,
  z down; the origin is the autopilot's local origin). Every JSON record is in it.
- `local_enu`: the same origin with ENU axes (x east, y north, z up; `companion.wire.frames`'s
  swap), what viewers expect: every 3D channel is in it.
- `vehicle`: the body, FLU (x forward, y left, z up), placed by `/viz/tf`.
"""

from __future__ import annotations

import dataclasses
import enum
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

FRAMES_NOTE = ("JSON records: local_ned (the autopilot's local NED frame); 3D channels: local_enu (same "
               "origin, ENU axes); vehicle: body FLU placed by /viz/tf")


@dataclass(frozen=True)
class Spec:
    schema_name: str
    schema_encoding: str  # "jsonschema" | "protobuf"
    schema_data: bytes
    message_encoding: str  # "json" | "protobuf"


def _obj(title: str, description: str, properties: dict[str, Any] | None = None,
         required: tuple[str, ...] = ()) -> dict[str, Any]:
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", "title": title,
            "description": description, "type": "object", "properties": properties or {},
            "required": list(required)}


NUM = {"type": "number"}
T_MONO = {"type": "number", "description": "monotonic clock of the companion (s) when it happened"}

INBOUND = _obj("bezier.InboundMessage", "A Zenoh message as the companion received it (frame: the sender's)", {
    "key": {"type": "string"}, "t": T_MONO, "bytes": {"type": "integer"},
    "text": {"type": "string", "description": "the payload, when it is UTF-8"},
    "base64": {"type": "string", "description": "the payload, when it is not UTF-8"},
    "oversized": {"type": "boolean", "description": "over [limits] max_message_bytes: not kept"},
}, ("key", "t", "bytes"))

MAVLINK = _obj("bezier.MavlinkMessage", "A MAVLink message, decoded by pymavlink (local_ned for *_NED messages)", {
    "mavpackettype": {"type": "string", "description": "the message name"}, "t": T_MONO,
    "sysid": {"type": "integer"}, "compid": {"type": "integer"},
}, ("mavpackettype", "t"))

PLAN = _obj("bezier.PlannerCall", "One planner call: inputs, outputs (local_ned), timings", {
    "seq": {"type": "integer"}, "function": {"type": "string"},
    "where": {"type": "string", "enum": ["process", "thread"]}, "compiled": {"type": "boolean"},
    "submitted": T_MONO, "done": T_MONO, "latency_ms": NUM, "ok": {"type": ["boolean", "null"]},
    "status": {"type": ["string", "null"]}, "message": {"type": ["string", "null"]},
    "stats": {"type": "object"}, "trajectory": {"type": ["object", "null"]},
    "fingerprint": {"type": "string", "description": "sha256 of the result without timing stats"},
    "call": {"type": ["string", "null"], "description": "pickle (base64) of (function, arguments)"},
    "result": {"type": ["string", "null"], "description": "pickle (base64) of the result"},
}, ("seq", "function", "submitted", "done", "fingerprint"))

STATS = _obj("bezier.RecorderStats", "The recorder's own counts", {
    "t": T_MONO, "written": {"type": "integer"}, "dropped": {"type": "object"},
    "dropped_total": {"type": "integer"}, "queued": {"type": "integer"},
}, ("written", "dropped_total"))

FLIGHT_STATE = {"type": "object", "description": "companion.flight.FlightState: the state and the flags about "
                "the vehicle's situation", "properties": {
                    "state": {"type": "string"}, "airborne": {"type": "boolean"}, "seen_link": {"type": "boolean"},
                    "link_lost": {"type": "boolean"}, "exit_requested": {"type": "boolean"},
                    "disarm_requested": {"type": "boolean"}, "starting": {"type": "boolean"},
                    "ground_z": {"type": ["number", "null"]}},
                "required": ["state"]}
TAGGED = {"type": "object", "properties": {"type": {"type": "string", "description": "the class name"},
                                           "fields": {"type": "object"}}, "required": ["type", "fields"]}
TRANSITION = _obj("bezier.SupervisorTransition", "One Supervisor.handle call (companion/supervisor.py): the event, "
                  "the flight state before and after, the actions", {
    "seq": {"type": "integer", "description": "1, 2, ... per run, numbered as handle ran: a gap is a record "
            "the recorder dropped (its queue was full)"},
    "t": T_MONO, "event": TAGGED, "before": FLIGHT_STATE, "after": FLIGHT_STATE,
    "actions": {"type": "array", "items": TAGGED},
    "pickle": {"type": ["string", "null"], "description": "pickle (base64) of (before, event, after, actions)"},
}, ("seq", "t", "event", "before", "after", "actions", "pickle"))

# the numbering of a decision's records (a rules' call, each recorded)
SEQ_RULES = {"type": "integer", "description": "1, 2, ... per run, numbered as the rules ran: a gap is a record the "
             "recorder dropped"}
STEP = _obj("bezier.AutopilotStep", "One call of the autopilot watch's rules (companion/autopilot_rules.py "
            "watch_step): a reading of what the autopilot reported (or a link check), the watch's state before and "
            "after, the flight state the rules read, the supervisor events and other outputs", {
    "seq": SEQ_RULES,
    "t": {"type": "number", "description": "the time the rules were given: the companion's monotonic clock (s), "
          "an input of the rules"},
    "transition": {"type": "integer", "description": "the /supervisor/transition seq its first event got (the "
                   "next one when it made none)"},
    "reading": TAGGED, "flight": FLIGHT_STATE,
    "before": {"type": "object", "description": "companion.autopilot_rules.WatchState (null: infinite)"},
    "after": {"type": "object"}, "outputs": {"type": "array", "items": TAGGED},
    "pickle": {"type": ["string", "null"], "description": "pickle (base64) of (before, flight, reading, now, after, "
               "outputs)"},
}, ("seq", "t", "transition", "reading", "flight", "before", "after", "outputs", "pickle"))

_TRAJ = {"type": "object", "description": "a trajectory's span (trajectory time, s) and segment count",
         "properties": {"t0": NUM, "t_end": NUM, "segments": {"type": "integer"}}}
SWAP = _obj("bezier.ControlSwap", "One decision of the swap's rule (companion/control.py swap_refusal): whether a "
            "new plan replaced the flown one from its split, decided from these values alone", {
    "seq": {"type": "integer", "description": "1, 2, ... per run, numbered as the rule ran: a gap is a record the "
            "recorder dropped"},
    "t": T_MONO, "what": {"type": "string", "description": "what asked for the swap"},
    "now": {"type": "number", "description": "trajectory time (s) when decided"},
    "lead": {"type": "number", "description": "s the setpoints were sampled ahead"},
    "rate_hz": NUM, "t_split": {"type": "number", "description": "trajectory time the new plan flies from"},
    "refusal": {"type": "string", "description": "why the swap was refused; empty: swapped in"},
    "old": _TRAJ, "new": _TRAJ,
    "pickle": {"type": ["string", "null"], "description": "pickle (base64) of (the flown trajectory, the new one)"},
}, ("seq", "t", "what", "now", "lead", "rate_hz", "t_split", "refusal", "pickle"))
TRACKING_STATE = {"type": "object", "description": "companion.tracking_rules.TrackingState as recorded (StateSeen): "
                  "the samples in a row over the limit, whether the tracking event and the margin warning were "
                  "made, the window of recent errors by its length and a CRC-32 (the errors are the readings of "
                  "the records before)", "properties": {
                      "over": {"type": "integer"}, "said": {"type": "boolean"}, "nearing_said": {"type": "boolean"},
                      "errors": {"type": "integer"}, "digest": {"type": "string"}},
                  "required": ["over", "said", "nearing_said", "errors", "digest"]}
TRACKING_STEP = _obj("bezier.TrackingStep", "One call of the tracking error's rules (companion/tracking_rules.py "
                     "tracking_step) that changed their state or said something: a position sample's error and the "
                     "moment's facts, the state before and after, the outputs (events, a brake); every value exact, as "
                     "JSON holds it (no pickle)", {
    "seq": SEQ_RULES,
    "t": T_MONO,
    "transition": {"type": "integer", "description": "the /supervisor/transition seq next after the call: a brake's "
                   "Braking transition comes at or after it"},
    "reading": TAGGED, "before": TRACKING_STATE, "after": TRACKING_STATE,
    "outputs": {"type": "array", "items": TAGGED},
    "window": {"type": ["array", "null"], "items": NUM, "description": "the errors before, in full, in the first "
               "record of a file or after a gap (null: the readings before make them)"},
}, ("seq", "t", "transition", "reading", "before", "after", "outputs", "window"))

SPLIT_STEP = _obj("bezier.SplitStep", "One call of the split-and-swap loop's rules (companion/split_rules.py "
                  "split_step): for one plan made in flight, what was observed (the time committed, the plan's "
                  "outcome and how long it took, the fleet's answer, the swap's refusal, ...), the state before and "
                  "after, and what the loop did next; every value exact, as JSON holds it (no pickle)", {
    "seq": SEQ_RULES,
    "t": T_MONO,
    "swap": {"type": "integer", "description": "the /control/swap seq of the last swap decided then (a step "
             "that observed a swap: its record)"},
    "call": {"type": "integer", "description": "the at_split call (1, 2, ... per run): its steps chain"},
    "step": {"type": "integer", "description": "1, 2, ... within the call"},
    "what": {"type": "string", "description": "what asked for the plan"},
    "rules": {"type": "object", "description": "companion.split_rules.SplitRules: the call's givens"},
    "before": {"type": "object", "description": "companion.split_rules.SplitState"},
    "observation": TAGGED, "after": {"type": "object"}, "action": TAGGED,
}, ("seq", "t", "swap", "call", "step", "what", "rules", "before", "observation", "after", "action"))

COMMIT_STEP = _obj("bezier.CommitStep", "One call of the fleet's commit protocol (companion/commit.py step): a "
                   "candidate ready with what was known of the others, another vehicle's trajectory heard, a tick, "
                   "a cancel; the protocol's state before and after and its actions; every value exact, as JSON "
                   "holds it (no pickle)", {
    "seq": SEQ_RULES,
    "t": T_MONO,
    "before": {"type": "object", "description": "companion.commit.State: our rank, the wait, the phase, the "
               "candidate's number, its deadline"},
    "event": TAGGED,
    "after": {"type": "object"},
    "actions": {"type": "array", "items": TAGGED},
}, ("seq", "t", "before", "event", "after", "actions"))

CLOCK_SAMPLE = _obj("bezier.ClockSample", "One sample of the fleet's clock check (companion/clocks.py): another "
                    "vehicle's trajectory put, sent on its clock and heard on ours (system clock, s), and the "
                    "verdict on our clock then", {
    "seq": SEQ_RULES,
    "t": T_MONO,
    "vehicle": {"type": "string"},
    "sent": {"type": "number", "description": "the put's send time on its sender's system clock (attachment)"},
    "arrived": {"type": "number", "description": "our system clock when it arrived"},
    "off": {"type": ["string", "null"], "description": "why our clock is taken to be off then (null: it agrees)"},
}, ("seq", "t", "vehicle", "sent", "arrived", "off"))

BUDGET_STEP = _obj("bezier.BudgetStep", "One question to the plan budget (companion/plan_budget.py budget_step): how "
                   "far ahead a plan is split and how many candidate plans a search may plan, from the planning "
                   "times measured in this service, or a plan's time measured into it; every value exact, as JSON "
                   "holds it (no pickle)", {
    "seq": SEQ_RULES,
    "t": T_MONO,
    "before": {"type": "object", "description": "companion.plan_budget.Budget: seconds per candidate plan per "
               "waypoint, as estimated before"},
    "ask": TAGGED,
    "after": {"type": "object", "description": "companion.plan_budget.Budget (changed by Measured only)"},
    "answer": {"type": ["number", "null"], "description": "seconds ahead, or candidate plans (null: no cap, or "
               "nothing to answer)"},
}, ("seq", "t", "before", "ask", "after", "answer"))

RACE_STEP = _obj("bezier.RaceStep", "One call of a pop-up obstacle's rules (companion/race_rules.py race_step): at the "
                 "pop-up, a deadline brought forward, each turn of the race of its replan against the braking deadline, "
                 "its end; the observation, the state before and after, the action; every value exact (JSON, no pickle)", {
    "seq": SEQ_RULES, "t": T_MONO,
    "transition": {"type": "integer", "description": "the /supervisor/transition seq next after the call: a brake's "
                   "Braking transition comes at or after it"},
    "call": {"type": "integer", "description": "the pop-up (1, 2, ... per run): its steps chain"},
    "step": {"type": "integer", "description": "1, 2, ... within the pop-up"}, "what": {"type": "string"},
    "rules": {"type": "object", "description": "companion.race_rules.RaceRules: the pop-up's givens"},
    "before": {"type": "object", "description": "companion.race_rules.RaceState"},
    "observation": TAGGED, "after": {"type": "object"}, "action": TAGGED,
}, ("seq", "t", "transition", "call", "step", "what", "rules", "before", "observation", "after", "action"))

COMMAND_STEP = _obj("bezier.CommandStep", "One call of an operator command sequence's rules "
                    "(companion/command_rules.py command_step): for one run of a sequence (arm, takeoff, its climb, "
                    "land, abort, disarm, how a command ended, ...), what was observed (the autopilot's answer or "
                    "its timeout, the mode and armed state, the climb's swap), the state before and after, and what "
                    "the sequence did next; every value exact, as JSON holds it (no pickle)", {
    "seq": SEQ_RULES,
    "t": T_MONO,
    "transition": {"type": "integer", "description": "the /supervisor/transition seq the next transition gets (a "
                   "step whose action is a Transition: the one it makes)"},
    "call": {"type": "integer", "description": "the sequence's run (1, 2, ... per run of the service): its steps "
             "chain"},
    "step": {"type": "integer", "description": "1, 2, ... within the run"},
    "rules": {"type": "object", "description": "companion.command_rules.CommandRules: the run's sequence and givens"},
    "before": {"type": "object", "description": "companion.command_rules.CommandState"},
    "observation": TAGGED, "after": {"type": "object"}, "action": TAGGED,
}, ("seq", "t", "transition", "call", "step", "rules", "before", "observation", "after", "action"))

STALL_STEP = _obj("bezier.StallStep", "One call of the stall rules (companion/stall_rules.py stall_step) that changed "
                  "their state, found a stall or settled: the loop's beat (its gap, the setpoint sender's latch, the time since a "
                  "setpoint left, control, the flight state) or the flight state once a stall was dealt with; the state "
                  "before and after; the action (quiet, or the stall and what to do: nothing, hold, release control); "
                  "every value exact (JSON, no pickle)", {
    "seq": SEQ_RULES, "t": T_MONO,
    "transition": {"type": "integer", "description": "the /supervisor/transition seq the next transition gets: a "
                   "hold or a release after a stall makes its transitions at or after it"},
    "rules": {"type": "object", "description": "companion.stall_rules.StallRules"},
    "before": {"type": "object", "description": "companion.stall_rules.StallState"},
    "observation": TAGGED, "after": {"type": "object"}, "action": TAGGED,
}, ("seq", "t", "transition", "rules", "before", "observation", "after", "action"))

HOLD_STEP = _obj("bezier.HoldStep", "One call of the hand-over's hold rules (companion/hold_rules.py hold_step): "
                 "where the hold began or a sample of the vehicle (armed, mode, altitude, velocity), the state before "
                 "and after, and the verdict (watch on, holds, fails and why); every value exact (JSON, no pickle)", {
    "seq": SEQ_RULES, "t": T_MONO,
    "call": {"type": "integer", "description": "the hold watched (1, 2, ... per run): its steps chain"},
    "step": {"type": "integer", "description": "1, 2, ... within the hold"},
    "rules": {"type": "object", "description": "companion.hold_rules.HoldRules: the autopilot's hold profile"},
    "before": {"type": "object", "description": "companion.hold_rules.HoldState"},
    "observation": TAGGED, "after": {"type": "object"}, "action": TAGGED,
}, ("seq", "t", "call", "step", "rules", "before", "observation", "after", "action"))

CHOICE_STEP = _obj("bezier.ChoiceStep", "One call of the navigator's plan choice (companion/choice_rules.py "
                   "choice_step): which planner call a mission's start, a replan, a stop or a quick start's "
                   "improvement asks for and what it makes of the answer, and what the start command does; every "
                   "value exact (JSON, no pickle)", {
    "seq": SEQ_RULES, "t": T_MONO,
    "call": {"type": "integer", "description": "the run (1, 2, ... per run of the service: a start, a replan, a "
             "stop, an improvement, a start command): its steps chain"},
    "step": {"type": "integer", "description": "1, 2, ... within the run"},
    "rules": TAGGED, "before": {"type": "object", "description": "companion.choice_rules.ChoiceState"},
    "observation": TAGGED, "after": {"type": "object"}, "action": TAGGED,
}, ("seq", "t", "call", "step", "rules", "before", "observation", "after", "action"))

DECODED = _obj("bezier.DecodedMessage", "An inbound message as the companion read it (companion.wire.messages.read): "
               "the typed message (local_ned) or the refusal, and what read was given besides the bytes", {
    "seq": {"type": "integer", "description": "1, 2, ... per run, numbered as the message was read: a gap is a "
            "record the recorder dropped"},
    "key": {"type": "string"}, "t": T_MONO,
    "ok": {"type": "boolean", "description": "false: refused (field, reason)"},
    "type": {"type": "string", "description": "the typed message's class, or the error's"},
    "field": {"type": ["string", "null"]}, "reason": {"type": ["string", "null"]},
    "fingerprint": {"type": "string", "description": "sha256 of the typed message (or of the refusal)"},
    "call": {"type": ["string", "null"], "description": "pickle (base64) of (key, payload, home, home_pending, fleet, autopilot)"},
}, ("seq", "key", "t", "ok", "type", "fingerprint"))

NUM_OR_NULL = {"type": ["number", "null"], "description": "null: unbounded"}
BOUNDS = _obj("bezier.Bounds", "The bounds a plan used, per derivative order (SI units): the tightest over "
              "the axes, and the per-axis box (local_ned; rows velocity..snap, columns x, y, z)", {
    "t": T_MONO, "velocity": NUM_OR_NULL, "acceleration": NUM_OR_NULL, "jerk": NUM_OR_NULL, "snap": NUM_OR_NULL,
    "lo": {"type": "array"}, "hi": {"type": "array"},
}, ("velocity", "acceleration", "jerk", "snap"))

OUT_DESCRIPTIONS = {
    "status": "Status as published on <prefix>/<vehicle>/status (README: Zenoh interface)",
    "telemetry": "Telemetry as published (local_ned)",
    "trajectory": "The plan flown, as published (local_ned; segments with corridors)",
    "events": "Events as published",
}


def _maybe(kind: str) -> dict[str, Any]:
    return {"type": [kind, "null"]}


VEC = {"type": ["array", "null"], "items": NUM}
# the fields a viewer plots or filters on (a viewer completes message paths from these);
# the README's "The Zenoh interface" has them all
OUT_PROPERTIES: dict[str, dict[str, Any]] = {
    "status": {
        "vehicle": {"type": "string"}, "time": NUM, "state": {"type": "string"}, "airborne": {"type": "boolean"},
        "mode": _maybe("string"), "armed": {"type": "boolean"}, "link": {"type": "boolean"},
        "streaming": {"type": "boolean"}, "mission": _maybe("string"), "progress": _maybe("number"),
        "time_to_go": _maybe("number"), "tracking_error": _maybe("number"),
        "tracking_error_max": _maybe("number"), "lag_estimate_ms": _maybe("number"),
        "accel_lead": NUM, "accel_lead_tc": NUM,
        "aim_horizontal": {"type": "array", "items": {"type": "array", "items": NUM},
                           "description": "[setpoints] aim_horizontal's terms in use: [k s², tc s]"},
        "message_to_setpoint_ms": _maybe("number"), "plan_latency_ms": _maybe("number"),
        "replan_latency_ms": _maybe("number"), "setpoints_sent": {"type": "integer"},
        "setpoint_gap_max_ms": NUM, "gc_pause_max_ms": NUM, "setpoints_stalled": {"type": "boolean"},
        "recording": {"type": "object", "properties": {
            "file": _maybe("string"), "written": {"type": "integer"}, "dropped": {"type": "integer"},
            "error": _maybe("string")}},
        "fleet": {"type": ["object", "null"], "description": "null without [fleet] origin (docs/fleet.md)",
                  "properties": {"placed": {"type": "boolean"}, "source": _maybe("string"), "offset_ned": VEC}},
    },
    "telemetry": {
        "time": NUM, "frame": {"type": "string"}, "position": VEC, "velocity": VEC,
        "attitude": {"type": "object", "properties": {"roll": _maybe("number"), "pitch": _maybe("number"),
                                                      "yaw": _maybe("number")}},
        "armed": {"type": "boolean"}, "mode": _maybe("string"),
    },
    "events": {"type": {"type": "string"}, "time": NUM, "state": {"type": "string"}, "message": {"type": "string"}},
    "trajectory": {"frame": {"type": "string"}, "segments": {"type": "array"}},
}

FOXGLOVE = {
    "/viz/vehicle": "PoseInFrame",
    "/viz/tf": "FrameTransform",
    "/viz/planned_path": "PosesInFrame",
    "/viz/flown_path": "PosesInFrame",
    "/viz/obstacles": "SceneUpdate",
    "/viz/corridors": "SceneUpdate",
}


def _json(schema: dict[str, Any]) -> Spec:
    return Spec(schema["title"], "jsonschema", json.dumps(schema).encode(), "json")


@cache
def spec(topic: str) -> Spec:
    """The schema of a channel, from its name."""
    if topic in FOXGLOVE:
        from foxglove import messages

        s = getattr(messages, FOXGLOVE[topic]).get_schema()
        return Spec(s.name, s.encoding, bytes(s.data), "protobuf")
    if topic.startswith("/in/"):
        return _json(INBOUND)
    if topic.startswith("/out/"):
        key = topic.removeprefix("/out/")
        return _json(_obj(f"bezier.{key}", OUT_DESCRIPTIONS.get(key, "as published"), OUT_PROPERTIES.get(key)))
    if topic.startswith("/mavlink/"):
        return _json(MAVLINK)
    if topic == "/planner/plan":
        return _json(PLAN)
    if topic == "/supervisor/transition":
        return _json(TRANSITION)
    if topic == "/autopilot/step":
        return _json(STEP)
    if topic == "/control/swap":
        return _json(SWAP)
    if topic == "/tracking/step":
        return _json(TRACKING_STEP)
    if topic == "/navigator/split":
        return _json(SPLIT_STEP)
    if topic == "/navigator/budget":
        return _json(BUDGET_STEP)
    if topic == "/brakes/race":
        return _json(RACE_STEP)
    if topic == "/fleet/commit":
        return _json(COMMIT_STEP)
    if topic == "/fleet/clock":
        return _json(CLOCK_SAMPLE)
    if topic == "/commands/step":
        return _json(COMMAND_STEP)
    if topic == "/stalls/step":
        return _json(STALL_STEP)
    if topic == "/handover/hold":
        return _json(HOLD_STEP)
    if topic == "/navigator/choice":
        return _json(CHOICE_STEP)
    if topic == "/inbound/decoded":
        return _json(DECODED)
    if topic == "/recorder/stats":
        return _json(STATS)
    if topic == "/viz/bounds":
        return _json(BOUNDS)
    raise KeyError(f"no schema for channel {topic}")


# -- JSON records -------------------------------------------------------------------------------


def _finite(x: Any) -> Any:
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, dict):
        return {str(k): _finite(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_finite(v) for v in x]
    if isinstance(x, bytes | bytearray):
        return x.decode("utf-8", "replace")
    if isinstance(x, np.ndarray):
        return _finite(x.tolist())
    if isinstance(x, np.generic):
        return _finite(x.item())
    return x


def dumps(obj: Any) -> bytes:
    """JSON; NaN and infinities (MAVLink's "unset" NaN parameters) become null."""
    try:  # the common case, without a walk over every value
        return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()
    except (ValueError, TypeError):
        return json.dumps(_finite(obj), separators=(",", ":"), default=str).encode()


def inbound_record(key: str, payload: Any, t: float) -> bytes:
    body: dict[str, Any] = {"key": key, "t": t, "bytes": len(payload)}
    if isinstance(payload, bytes | bytearray | memoryview):
        raw = bytes(payload)
        try:
            body["text"] = raw.decode("utf-8")
        except UnicodeDecodeError:
            import base64

            body["base64"] = base64.b64encode(raw).decode()
    else:
        body["oversized"] = True
    return dumps(body)


def mavlink_record(msg: Any, t: float) -> bytes:
    d = msg.to_dict()
    d["t"] = t
    d["sysid"], d["compid"] = msg.get_srcSystem(), msg.get_srcComponent()
    return dumps(d)


_FIELD_NAMES: dict[type, tuple[str, ...] | None] = {}


def _field_names(kind: type) -> tuple[str, ...] | None:
    """A data class's field names (None: not a data class), once per class: the decisions'
    records convert tens of values a second on the writer thread."""
    if kind not in _FIELD_NAMES:
        _FIELD_NAMES[kind] = tuple(f.name for f in dataclasses.fields(kind)) if dataclasses.is_dataclass(kind) else None
    return _FIELD_NAMES[kind]


def _plain(x: Any) -> Any:
    """A supervisor value as JSON: enums by value, data classes and mappings as objects, an
    infinite time (never) as null, as `dumps` would write it (without its slower second pass)."""
    if x is None or isinstance(x, bool | int | str):
        return x
    if isinstance(x, float):
        return x if math.isfinite(x) else None
    if isinstance(x, enum.Enum):
        return x.value
    names = _field_names(type(x))
    if names is not None:
        return {n: _plain(getattr(x, n)) for n in names}
    if isinstance(x, Mapping):
        return {str(k): _plain(v) for k, v in x.items()}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    return x


def _tagged(x: Any) -> dict[str, Any]:
    return {"type": type(x).__name__, "fields": _plain(x)}


def transition_fields(before: Any, event: Any, after: Any, actions: tuple[Any, ...]) -> dict[str, Any]:
    """The readable part of a /supervisor/transition record (replay checks it against the
    record's pickle, so what a viewer shows is what was replayed)."""
    return {"event": _tagged(event), "before": _plain(before), "after": _plain(after),
            "actions": [_tagged(a) for a in actions]}


def step_fields(before: Any, flight: Any, reading: Any, now: float, after: Any,
                outputs: tuple[Any, ...]) -> dict[str, Any]:
    """The readable part of an /autopilot/step record (replay checks it against the pickle)."""
    return {"t": now, "reading": _tagged(reading), "flight": _plain(flight), "before": _plain(before),
            "after": _plain(after), "outputs": [_tagged(o) for o in outputs]}


def traj_span(traj: Any) -> dict[str, Any]:
    return {"t0": float(traj.t0), "t_end": float(traj.t_end), "segments": int(len(traj.times) - 1)}


def swap_fields(what: str, now: float, lead: float, rate_hz: float, t_split: float, old: Any, new: Any,
                refusal: str) -> dict[str, Any]:
    """The readable part of a /control/swap record (replay checks it against the pickle)."""
    return {"what": what, "now": now, "lead": lead, "rate_hz": rate_hz, "t_split": t_split, "refusal": refusal,
            "old": traj_span(old), "new": traj_span(new)}
def tracking_fields(before: Any, reading: Any, after: Any, outputs: tuple[Any, ...],
                    window: tuple[float, ...] | None) -> dict[str, Any]:
    """The readable part of a /tracking/step record (replay checks it against the pickle)."""
    return {"reading": _tagged(reading), "before": _plain(before), "after": _plain(after),
            "outputs": [_tagged(o) for o in outputs], "window": None if window is None else list(window)}


def rule_fields(rules: Any, before: Any, observation: Any, after: Any, action: Any) -> dict[str, Any]:
    """The body of a record of one call of a decision rule (companion.rule_run.RuleRun): the
    rules, the state before and after, the observation and the action; JSON only."""
    return {"rules": _plain(rules), "before": _plain(before), "observation": _tagged(observation),
            "after": _plain(after), "action": _tagged(action)}


def split_fields(call: int, step: int, what: str, rules: Any, before: Any, observation: Any, after: Any,
                 action: Any) -> dict[str, Any]:
    """The readable part of a /navigator/split (and /brakes/race) record: all of it (JSON only)."""
    return {"call": call, "step": step, "what": what, **rule_fields(rules, before, observation, after, action)}


def command_fields(call: int, step: int, rules: Any, before: Any, observation: Any, after: Any,
                   action: Any) -> dict[str, Any]:
    """The readable part of a /commands/step (and /handover/hold) record: all of it (JSON only)."""
    return {"call": call, "step": step, **rule_fields(rules, before, observation, after, action)}


def choice_fields(call: int, step: int, rules: Any, before: Any, observation: Any, after: Any,
                  action: Any) -> dict[str, Any]:
    """The readable part of a /navigator/choice record: all of it (JSON only; the rules tagged:
    a start's, a replan's or a stop's)."""
    return {**command_fields(call, step, rules, before, observation, after, action), "rules": _tagged(rules)}


def commit_fields(before: Any, event: Any, after: Any, actions: tuple[Any, ...]) -> dict[str, Any]:
    """A /fleet/commit record's body but for seq and t: all of it (JSON only)."""
    return {"before": _plain(before), "event": _tagged(event), "after": _plain(after),
            "actions": [_tagged(a) for a in actions]}


def budget_fields(before: Any, ask: Any, after: Any, answer: Any) -> dict[str, Any]:
    """A /navigator/budget record's body but for seq and t: all of it (JSON only)."""
    return {"before": _plain(before), "ask": _tagged(ask), "after": _plain(after), "answer": answer}


ORDERS = ("velocity", "acceleration", "jerk", "snap")


def bounds_fields(bounds: Any) -> dict[str, Any]:
    """Per order, the tightest magnitude over the axes (a number to plot over time), and the
    per-axis box (NED, lo and hi; null: unbounded)."""
    lo, hi = np.asarray(bounds.lo, dtype=float), np.asarray(bounds.hi, dtype=float)
    tight = np.minimum(hi, -lo).min(axis=1)
    return {**{n: float(tight[i]) for i, n in enumerate(ORDERS)}, "lo": lo.tolist(), "hi": hi.tolist()}
