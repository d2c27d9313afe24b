"""What the autopilot tells us and the MAVLink values the companion reads and sends: the
vehicle's state as last reported, the autopilot's words around a refusal, the modes, masks and
telemetry rates, and the decoding of modes and parameters (pure: no socket here; the link is
companion.wire.mavlink)."""

from __future__ import annotations

import collections
import math
import os
import struct
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil

from companion.wire import dialect

dialect.install()  # PX4 >= 1.14 says what happens in EVENT (410), which pymavlink lacks
mavlink = mavutil.mavlink

# EXTENDED_SYS_STATE landed_state (MAV_LANDED_STATE)
MAV_LANDED_ON_GROUND = mavlink.MAV_LANDED_STATE_ON_GROUND
MAV_LANDED_IN_AIR = mavlink.MAV_LANDED_STATE_IN_AIR
MAV_LANDED_TAKEOFF = mavlink.MAV_LANDED_STATE_TAKEOFF
MAV_LANDED_LANDING = mavlink.MAV_LANDED_STATE_LANDING
# Position + velocity + acceleration + yaw: only the yaw-rate bit is set.
TYPE_MASK = 2048
PX4_OFFBOARD = 6
APM_GUIDED = 4
APM_LAND = 9
# Modes the companion may hand over to, as (DO_SET_MODE param2, param3) and as decoded
# from the heartbeat (mavutil.mode_string_v10 names).
# PX4's "LOITER" is AUTO.LOITER (autonomous); POSCTL and ALTCTL are pilot modes.
PX4_MODES: dict[str, tuple[int, int]] = {"LOITER": (4, 3), "RTL": (4, 5), "LAND": (4, 6), "POSCTL": (3, 0),
                                         "ALTCTL": (2, 0)}
APM_MODES: dict[str, int] = {"STABILIZE": 0, "ALT_HOLD": 2, "GUIDED": 4, "LOITER": 5, "RTL": 6, "LAND": 9,
                             "POSHOLD": 16, "BRAKE": 17}
# Position only (velocity, acceleration and yaw rate ignored): ArduPilot's GUIDED holds such a
# target with no timeout (mode_guided.cpp pos_control_run; docs/handover.md).
POSITION_ONLY_MASK = 8 | 16 | 32 | 64 | 128 | 256 | 2048
# RC_CHANNELS: a transmitter is live when heard this recently (s) ...
RC_FRESH = 1.0
# ... and its throttle stick is centred (us): ArduCopter's pilot modes then climb at 0
# (ArduCopter/Attitude.cpp get_pilot_desired_climb_rate, the deadband around mid-stick).
RC_MID_STICK = (1400, 1600)

# The telemetry the companion uses, at the rate it asks for (Hz). HEARTBEAT is unsolicited.
WANTED: dict[str, float] = {"LOCAL_POSITION_NED": 30.0, "ATTITUDE": 10.0, "EXTENDED_SYS_STATE": 2.0}
# ArduPilot's legacy stream groups (REQUEST_DATA_STREAM) carrying them, and the suffix of the
# parameter that sets each group's rate at boot on the link's port (MAVn_* from 4.7, SRn_* before).
APM_STREAMS: dict[str, tuple[int, str]] = {
    "LOCAL_POSITION_NED": (mavlink.MAV_DATA_STREAM_POSITION, "POSITION"),
    "ATTITUDE": (mavlink.MAV_DATA_STREAM_EXTRA1, "EXTRA1"),
    "EXTENDED_SYS_STATE": (mavlink.MAV_DATA_STREAM_EXTENDED_STATUS, "EXT_STAT"),
}
APM_MAVN_FROM = (4, 7)  # the SRn_* rate parameters became MAVn_* in ArduPilot 4.7
POSITION_STALE = 1.0  # s without LOCAL_POSITION_NED: no position estimate
# What the autopilot says (EVENT, STATUSTEXT) this long before a refusing COMMAND_ACK, or up
# to NOTE_AFTER after it, is taken as the refusal's reason.
NOTE_BEFORE = 1.0
NOTE_AFTER = 0.3

# heartbeats of these types are other components on the link, not an autopilot
IGNORED_TYPES = {
    mavlink.MAV_TYPE_GCS,
    mavlink.MAV_TYPE_ONBOARD_CONTROLLER,
    mavlink.MAV_TYPE_GIMBAL,
    mavlink.MAV_TYPE_ADSB,
}


def result_name(result: int) -> str:
    """MAV_RESULT's name for a COMMAND_ACK result (the number when unknown)."""
    entry = mavlink.enums["MAV_RESULT"].get(result)
    return entry.name if entry is not None else str(result)


@dataclass(frozen=True)
class Note:
    """Something the autopilot said: an EVENT (PX4 >= 1.14) or a STATUSTEXT."""

    at: float  # monotonic arrival
    source: str  # "event" | "statustext"
    text: str  # the event in words (PX4's events metadata), else "event <id> (why not)"; or the STATUSTEXT
    level: str  # EVENT log level or MAV_SEVERITY name, without its prefix
    event_id: int | None = None
    name: str | None = None  # the PX4 event name, when known
    words: bool = False  # the text is the autopilot's own wording (decoded event, or STATUSTEXT)

    def fields(self) -> dict[str, Any]:
        if self.source == "event":
            return {"event": {"id": self.event_id, "level": self.level, "name": self.name}}
        return {"statustext": {"text": self.text, "severity": self.level}}


class CommandFailed(RuntimeError):
    """A command sequence failed; `result` (MAV_RESULT name) and `note` (what the autopilot
    said around the refusal) when the autopilot refused a COMMAND_LONG. `by`: who refused,
    "autopilot" (it said no, did not answer, or did not do it in time) or "companion" (one of
    the companion's own checks: the operator's `send` exits 4, not 5, on it)."""

    def __init__(self, message: str, result: str | None = None, note: Note | None = None,
                 reasons: tuple[str, ...] = (), by: str = "autopilot") -> None:
        super().__init__(message)
        self.result = result
        self.note = note
        self.reasons = reasons  # what the autopilot said around the refusal, in words
        self.by = by  # who refused: "autopilot", or "companion" when its own check did

    def fields(self) -> dict[str, Any]:
        """For the `refused` event: the result code and the EVENT/STATUSTEXT, when known."""
        out: dict[str, Any] = {}
        if self.result is not None:
            out["result"] = self.result
        if self.note is not None:
            out.update(self.note.fields())
        if self.reasons:
            out["reasons"] = list(self.reasons)
        return out

    def chained(self, message: str) -> CommandFailed:
        """The same refusal with a longer message."""
        return CommandFailed(message, self.result, self.note, self.reasons, self.by)


@dataclass
class VehicleState:
    """What the autopilot last told us (NED, SI units, monotonic times)."""

    autopilot: str | None = None  # "px4" | "ardupilot"
    # the last heartbeat taken, as received (MAV_AUTOPILOT, MAV_TYPE, base_mode, custom_mode):
    # what `autopilot`, `mode` and `armed` were read from (recorded with the watch's readings)
    heartbeat_wire: tuple[int, int, int, int] | None = None
    mav_type: int = 0
    base_mode: int = 0
    custom_mode: int = 0
    mode: str = ""
    armed: bool = False
    system_status: int = 0
    last_heartbeat: float = -math.inf
    last_message: float = -math.inf  # any message from the autopilot's component (liveness)
    position: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))
    attitude: np.ndarray = field(default_factory=lambda: np.zeros(3))  # roll, pitch, yaw
    last_position: float = -math.inf
    received: dict[str, float] = field(default_factory=dict)  # message type -> last arrival
    landed_state: int = 0  # MAV_LANDED_STATE; 0 unknown
    last_landed_state: float = -math.inf  # when EXTENDED_SYS_STATE last arrived
    # HOME_POSITION's local x, y, z (NED, the autopilot's local frame); None until reported
    home: np.ndarray | None = None
    # PX4 sent HOME_POSITION at the local origin: home is not valid yet (the autopilot is not ready)
    home_pending: bool = False
    # HOME_POSITION's latitude, longitude (deg) and altitude (m AMSL), with `home`; None until reported
    home_lla: tuple[float, float, float] | None = None
    # GPS_GLOBAL_ORIGIN: the local frame's origin, (lat deg, lon deg, alt m AMSL); None until reported
    gps_origin: tuple[float, float, float] | None = None
    sw_version: tuple[int, int, int] | None = None  # AUTOPILOT_VERSION.flight_sw_version
    # why LOCAL_POSITION_NED is missing, once the companion has told the causes apart
    position_advice: str | None = None
    rc_throttle: int | None = None  # RC_CHANNELS chan3_raw (us), when the autopilot sends it
    last_rc: float = -math.inf
    notes: collections.deque[Note] = field(default_factory=lambda: collections.deque(maxlen=16))

    @property
    def has_position(self) -> bool:
        return bool(np.all(np.isfinite(self.position)))

    def position_problem(self, now: float | None = None) -> str | None:
        """Why there is no usable position estimate now (None: there is one)."""
        now = time.monotonic() if now is None else now
        if "LOCAL_POSITION_NED" not in self.received:
            hint = ("the autopilot has not sent LOCAL_POSITION_NED since the link came up (requested at "
                    f"{WANTED['LOCAL_POSITION_NED']:.0f} Hz); ")
            if self.position_advice is not None:
                hint += self.position_advice
            elif self.autopilot == "ardupilot":
                hint += "see the `telemetry` event for the cause (no EKF origin yet, or requests ignored)"
            else:
                hint += "check its position estimate (EKF2 / GPS or vision) and the MAVLink instance's mode"
            return f"no position estimate from the autopilot: {hint}"
        age = now - self.last_position
        if age > POSITION_STALE:
            return f"no position estimate from the autopilot: the last LOCAL_POSITION_NED is {age:.1f} s old"
        if not self.has_position:
            return "no position estimate from the autopilot: LOCAL_POSITION_NED is not finite"
        return None

    def pilot_sticks_live(self, now: float | None = None) -> bool:
        """A transmitter is heard (RC_CHANNELS within RC_FRESH) with the throttle centred."""
        now = time.monotonic() if now is None else now
        return (self.rc_throttle is not None and now - self.last_rc <= RC_FRESH
                and RC_MID_STICK[0] <= self.rc_throttle <= RC_MID_STICK[1])

    def in_follow_mode(self) -> bool:
        return follow_mode(self.autopilot, self.mode)

    def take(self, kind: str, msg: Any, now: float, autopilot_component: int) -> bool:
        """The one reader of the messages that say what the vehicle is and does (the link
        reads the rest: acknowledgements, parameters, PX4's events). False: a heartbeat that is
        not the autopilot's (a GCS, a camera, another component), to be ignored."""
        if kind != "HEARTBEAT":
            self.received[kind] = now
            if msg.get_srcComponent() == autopilot_component:
                self.last_message = now
        if kind == "HEARTBEAT":
            if msg.type in IGNORED_TYPES or msg.autopilot == mavlink.MAV_AUTOPILOT_INVALID:
                return False
            if msg.get_srcComponent() != autopilot_component:
                return False
            wire = (int(msg.autopilot), int(msg.type), int(msg.base_mode), int(msg.custom_mode))
            self.heartbeat_wire = wire
            self.autopilot, self.mode, self.armed = read_heartbeat(self.autopilot, *wire)
            self.mav_type, self.base_mode, self.custom_mode = wire[1:]
            self.system_status = msg.system_status
            self.last_heartbeat = now
        elif kind == "LOCAL_POSITION_NED":
            self.position = np.array([msg.x, msg.y, msg.z], dtype=float)
            self.velocity = np.array([msg.vx, msg.vy, msg.vz], dtype=float)
            self.last_position = now
        elif kind == "ATTITUDE":
            self.attitude = np.array([msg.roll, msg.pitch, msg.yaw], dtype=float)
        elif kind == "EXTENDED_SYS_STATE":
            self.landed_state = msg.landed_state
            self.last_landed_state = now
        elif kind == "HOME_POSITION":
            home = np.array([msg.x, msg.y, msg.z], dtype=float)
            if self.autopilot == "px4" and not np.any(home):
                # PX4 reports home at the local origin until its estimator is ready (~37 s after
                # boot on SIH 1.15) while its estimate on the ground drifts (z -0.9..+3.6 m, tens
                # of metres horizontally): not a home to place anything by (autopilot-facts.md).
                # A home reported before (a PX4 that rebooted) is no longer valid either.
                self.home_pending = True
                self.home, self.home_lla = None, None
            elif np.all(np.isfinite(home)):
                self.home = home
                self.home_pending = False
                if msg.latitude != 0 or msg.longitude != 0:  # 0, 0: no global position (a vehicle without GPS)
                    self.home_lla = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        elif kind == "GPS_GLOBAL_ORIGIN":
            if msg.latitude != 0 or msg.longitude != 0:
                self.gps_origin = (msg.latitude * 1e-7, msg.longitude * 1e-7, msg.altitude * 1e-3)
        elif kind == "AUTOPILOT_VERSION":
            v = int(msg.flight_sw_version)
            self.sw_version = ((v >> 24) & 0xFF, (v >> 16) & 0xFF, (v >> 8) & 0xFF)
        elif kind == "RC_CHANNELS":
            if int(msg.chancount) >= 3 and 800 <= int(msg.chan3_raw) <= 2200:
                self.rc_throttle = int(msg.chan3_raw)
                self.last_rc = now
        elif kind == "STATUSTEXT":
            sev = mavlink.enums["MAV_SEVERITY"].get(int(msg.severity))
            level = sev.name.removeprefix("MAV_SEVERITY_") if sev is not None else str(msg.severity)
            self.notes.append(Note(now, "statustext", str(msg.text), level, words=True))
        return True


def follow_mode(autopilot: str | None, mode: str) -> bool:
    """`mode` is the one in which the autopilot follows our setpoints (OFFBOARD, GUIDED)."""
    if autopilot == "px4":
        return mode == "OFFBOARD"
    return mode == "GUIDED"


def heard(last_heartbeat: float, last_message: float, timeout: float, now: float) -> bool:
    """The autopilot is heard at `now`: a heartbeat once, then any of its messages within
    `timeout` (the telemetry at tens of Hz, not only the 1 Hz heartbeat, so that a lossy
    radio link is not declared lost for two heartbeats missed in a row)."""
    if last_heartbeat == -math.inf:
        return False
    return now - max(last_heartbeat, last_message) <= timeout


def autopilot_name(code: int) -> str | None:
    if code == mavlink.MAV_AUTOPILOT_PX4:
        return "px4"
    if code == mavlink.MAV_AUTOPILOT_ARDUPILOTMEGA:
        return "ardupilot"
    return None


def read_heartbeat(known: str | None, autopilot: int, mav_type: int, base_mode: int,
                   custom_mode: int) -> tuple[str | None, str, bool]:
    """A heartbeat's (autopilot, mode name, armed) from its fields as received; `known`: the
    autopilot named before, kept when this one's MAV_AUTOPILOT names none. The link's one
    reading of a heartbeat, which replay runs again on the recorded fields."""
    name = autopilot_name(autopilot) or known
    return name, decode_mode(name, mav_type, base_mode, custom_mode), bool(base_mode & mavlink.MAV_MODE_FLAG_SAFETY_ARMED)


def decode_mode(autopilot: str | None, mav_type: int, base_mode: int, custom_mode: int) -> str:
    if autopilot == "px4":
        return str(mavutil.interpret_px4_mode(base_mode, custom_mode))
    mapping = mavutil.mode_mapping_bynumber(mav_type) or mavutil.mode_mapping_acm
    return str(mapping.get(custom_mode, f"Mode({custom_mode})"))


def param_name(raw: Any) -> str:
    """A PARAM_VALUE's param_id (char[16], NUL-padded unless 16 long) as text."""
    text = raw.decode("ascii", errors="replace") if isinstance(raw, bytes) else str(raw)
    return text.split("\x00", 1)[0]


def param_value(autopilot: str | None, ptype: int, value: float) -> float:
    """A PARAM_VALUE's value: PX4 sends integer types bytewise in the float field (its
    MAV_PROTOCOL_CAPABILITY_PARAM_ENCODE_BYTEWISE), ArduPilot casts them to float."""
    ints = (mavlink.MAV_PARAM_TYPE_UINT8, mavlink.MAV_PARAM_TYPE_INT8, mavlink.MAV_PARAM_TYPE_UINT16,
            mavlink.MAV_PARAM_TYPE_INT16, mavlink.MAV_PARAM_TYPE_UINT32, mavlink.MAV_PARAM_TYPE_INT32)
    if autopilot == "px4" and ptype in ints:
        raw = struct.pack("<f", value)
        return float(struct.unpack("<I" if ptype == mavlink.MAV_PARAM_TYPE_UINT32 else "<i", raw)[0])
    return float(value)


_NETWORK = ("udpin:", "udpout:", "udp:", "udpbcast:", "tcp:", "tcpin:")


def parse_url(url: str) -> tuple[str, int]:
    """(device, baud) for pymavlink: network URLs as they are; `serial:/dev/ttyX:921600`
    or `/dev/ttyX:921600` for a serial port (baud defaults to 57600)."""
    if url.startswith(_NETWORK):
        return url, 57600
    device = url.removeprefix("serial:")
    head, sep, tail = device.rpartition(":")
    if sep and tail.isdigit():
        return head, int(tail)
    return device, 57600


def serial_port(url: str) -> int | None:
    """The ArduPilot SERIALn port a link of this URL is on, where the URL tells it for certain:
    SITL's first TCP port (5760) and a USB CDC device are SERIAL0. None otherwise (ArduPilot
    does not say which port a message came in on)."""
    if url.startswith(("tcp:", "tcpin:")) and url.rsplit(":", 1)[-1] == "5760":
        return 0
    device = parse_url(url)[0]
    if device.startswith(("/dev/ttyACM", "/dev/serial/by-id/usb-ArduPilot")):
        return 0
    return None


def rate_parameter(group: str, url: str, sw_version: tuple[int, int, int] | None) -> str:
    """The rate parameter of a stream group on the port of a link of this URL, by the autopilot's
    version (SRn_* before 4.7, MAVn_* from 4.7); never a port number it cannot know."""
    n = serial_port(url)
    port = "SERIAL0" if n == 0 else "the serial port this link is on"
    if sw_version is not None and sw_version[:2] >= APM_MAVN_FROM:
        return f"MAVn_{group} (n: the MAVLink instance on {port})"
    if sw_version is not None:
        return f"SR0_{group}" if n == 0 else f"SRn_{group} (n: the MAVLink channel of {port})"
    where = f"SR0_{group}" if n == 0 else f"SRn_{group}"
    return (f"{where} before 4.7, MAVn_{group} from 4.7 (the autopilot did not send AUTOPILOT_VERSION; "
            f"n: the MAVLink instance on {port})")


def telemetry_hint(autopilot: str | None, missing: list[str], url: str, sw_version: tuple[int, int, int] | None) -> str:
    """What to set so that the autopilot sends the `missing` messages at all."""
    if autopilot == "ardupilot":
        return "set " + ", ".join(f"{rate_parameter(APM_STREAMS[m][1], url, sw_version)} (for {m})"
                                  for m in missing) + " to a rate in Hz"
    return ("PX4 streams these in its Onboard MAVLink mode: check MAV_n_MODE = Onboard on this link, or add "
            "'mavlink stream -r RATE -s MESSAGE' in the SD card's etc/extras.txt")
