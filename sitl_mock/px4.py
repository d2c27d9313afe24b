"""The PX4 flavour's rules that need state of their own: readiness, component metadata, MAVLink FTP.

- Not ready to arm until the estimator settles: PX4 1.15 SIH was ready ("Ready for takeoff!")
  36-37 s after boot (measured, /work/shared/autopilot-facts.md). Until then: arming is refused
  (TEMPORARILY_REJECTED) after PX4's arming-check report (Common.cpp Report::report: the
  arming-check summary, each failing check, the health summary) and
  commander_arm_denied_resolve_failures (Commander.cpp arm()); HOME_POSITION reads the local
  origin (0, 0, 0); LOCAL_POSITION_NED on the ground drifts tens of metres horizontally and
  its z wanders (-0.94 to +3.60 m on a ground at +1.6, as measured). When ready, the estimate is
  reset to where the vehicle stands, home is set there and a clean report follows.
  GPS_GLOBAL_ORIGIN comes once, 1.5 s after boot, long before ready (as measured).
- Component metadata as PX4 serves it: COMPONENT_METADATA on MAV_CMD_REQUEST_MESSAGE
  (src/modules/mavlink/streams/COMPONENT_METADATA.hpp: uri mftp://etc/extras/component_general.json.xz),
  the general metadata naming the events file (src/lib/component_information/generate_component_general.py
  layout; type 4 = COMP_METADATA_TYPE_EVENTS), both xz-compressed, over MAVLink FTP
  (src/modules/mavlink/mavlink_ftp.cpp: one session, OpenFileRO, ReadFile, BurstReadFile,
  TerminateSession, ResetSessions; NAKs with PX4's error codes).
"""

from __future__ import annotations

import json
import lzma
import math
import struct
from typing import TYPE_CHECKING, Any

import numpy as np
from pymavlink.dialects.v20 import common as mav

from . import events as ev
from . import mavwire

if TYPE_CHECKING:
    from .server import MockAutopilot

# Seconds from boot until PX4 SIH is ready to arm (measured 36-37 s). MockConfig.px4_ready_s
# (None) and --px4-ready-after default to it.
DEFAULT_READY_S = 36.5
# The estimate on the ground before ready (PX4 SIH at 9ececfdd, 5 boots, measured 2026-12-03):
# z between -0.94 and +3.60 on PX4's +1.6 ground, so ground_z - 0.27 +- 2.27 m, a slow wander;
# horizontally it drifted 23-42 m away from where the vehicle stood (an earlier session saw up
# to 72 m), then was reset at ready (home then set where the vehicle stands, e.g.
# [-0.24, -0.49, 1.48]). The mock drifts DRIFT_XY_M (MockConfig.px4_drift_m) along a direction
# drawn at each boot, growing smoothly from rest as (t / ready)^2 (a constant velocity error
# integrating, which is how an estimator without a position fix drifts; the shape was not
# measured, only the size) with the matching velocity in LOCAL_POSITION_NED, and at ready it
# reports the vehicle's own position again (the reset).
DRIFT_CENTRE = -0.27
DRIFT_AMPLITUDE = 2.27
DRIFT_PERIOD_S = 23.0
DRIFT_XY_M = 30.0
# GPS_GLOBAL_ORIGIN came once, 1.4-1.6 s after boot (measured, 5 boots), long before ready:
# the estimator's global origin is set by the first GPS fix and not moved by the reset at ready.
# PX4's stream (streams/GPS_GLOBAL_ORIGIN.hpp) sends only when the origin changes, and on
# MAV_CMD_REQUEST_MESSAGE. A mock ready sooner than this has its origin when it is ready.
ORIGIN_AT_S = 1.5
# In AUTO.LOITER in the air, PX4 SIH's reported estimate wanders (measured 2026-12-03, 10 switches
# from OFFBOARD to AUTO.LOITER on PX4 SIH at 9ececfdd: at rest, horizontal estimate speeds up to
# 0.47-0.52 m/s, an excursion of 0.55-0.87 m out and back over 5-10 s; vertical speeds up to
# 0.17-0.30 m/s and 0.15-0.18 m; 2 s after a switch at 3 m/s up to 0.67-0.79 m/s; after the
# companion's braked hand-overs, 2026-12-02, up to 0.50-0.65 m/s: the mock takes 0.6): when AUTO.LOITER follows OFFBOARD in the air (a hand-over, a
# pilot's takeover: the case measured), the mock's LOCAL_POSITION_NED makes excursions out to
# LOITER_WANDER_M and back at up to LOITER_WANDER_SPEED horizontally (along one direction, from
# rest at the mode's start: 1 - cos) and out to LOITER_WANDER_Z_M at up to LOITER_WANDER_Z_SPEED
# vertically.
LOITER_WANDER_M = 0.8
LOITER_WANDER_SPEED = 0.6
LOITER_WANDER_Z_M = 0.16
LOITER_WANDER_Z_SPEED = 0.28
LOITER_WANDER_DIR = np.array([math.cos(math.radians(30.0)), math.sin(math.radians(30.0)), 0.0])
# In OFFBOARD in the air, PX4 SIH's estimate strays from the setpoint it tracks too (measured
# 2026-12-03 on PX4 SIH at 9ececfdd, the companion's default config: holding a setpoint, the
# estimate went 0.41 m off it, so missions braked themselves at a 0.40 m tracking allowance 2.4-4.6 s
# after their start, "tracking error 0.41-0.43 m"; in flight the estimate was 0.26-0.28 m RMS off
# the truth horizontally; the companion's wait for the estimate under 0.2 m/s after a braked stop
# ran out in the hand-overs, while its climbs ended at rest). The mock's LOCAL_POSITION_NED makes
# excursions out to OFFBOARD_WANDER_M and back every OFFBOARD_WANDER_PERIOD_S (from rest where the
# vehicle leaves the ground in OFFBOARD or enters OFFBOARD in the air: 1 - cos), in a direction
# that turns once every OFFBOARD_WANDER_TURN_S, while the vehicle itself tracks the setpoint: RMS
# 0.61 x 0.42 = 0.26 m, at up to 0.36 m/s, under 0.2 m/s only near the excursion's return (about
# 0.8 s of every 4 s). The period and the turn are not measured: chosen so that rest is seen once
# per excursion, as the climbs saw it. Vertically it does not wander (not measured in OFFBOARD).
OFFBOARD_WANDER_M = 0.42
OFFBOARD_WANDER_PERIOD_S = 4.0
OFFBOARD_WANDER_TURN_S = 10.0
# PX4 sends its arming-check report when the checks' results change (Report::report: a
# difference not yet reported, at most every 2 s), never in answer to an arm (Commander::arm calls
# update() without forcing a report). Measured on PX4 SIH (9ececfdd, 5 boots): at 2.3-2.5 s and
# again at 4.4-4.6 s after boot, then nothing for 28-31 s until the estimator's attitude is valid
# (1.1-1.2 s before "Ready for takeoff!"), at ready, and on each later change; 6 refused arms
# were followed only by commander_arm_denied_resolve_failures. The mock reports at REPORTS_AT s
# after boot, when the attitude is valid and at ready (MockConfig.px4_report_every_s adds a
# report that often, for tests about the words rather than the timing).
REPORTS_AT = (2.4, 4.5)
ATTITUDE_BEFORE_READY_S = 1.2  # ATTITUDE starts once the attitude is valid, this long before ready

GENERAL_URI = "mftp://etc/extras/component_general.json.xz"
EVENTS_URI = "mftp://etc/extras/all_events.json.xz"
COMP_METADATA_TYPE_EVENTS = 4
MSG_ID_COMPONENT_METADATA = 397

# MAVLink FTP (https://mavlink.io/en/services/ftp.html; PX4 mavlink_ftp.h)
OP_NONE, OP_TERMINATE, OP_RESET, OP_LIST, OP_OPEN_RO, OP_READ = 0, 1, 2, 3, 4, 5
OP_BURST_READ = 15
OP_ACK, OP_NAK = 128, 129
ERR_FAIL, ERR_INVALID_SESSION, ERR_NO_SESSIONS, ERR_EOF, ERR_UNKNOWN, ERR_NOT_FOUND = 1, 4, 5, 6, 7, 10
DATA_MAX = 239  # 251-byte payload minus its 12-byte header
_HEADER = struct.Struct("<HBBBBBBI")
BURST_CHUNKS = 16  # packets per BurstReadFile answer before burst_complete (PX4 sends bursts per cycle)

# Modes that need a local position (modeCheck.cpp: their arming and run bits cleared while it
# is invalid), and those that can arm without one.
POSITION_MODES = ev.nav_groups("posctl", "mission", "loiter", "rtl", "offboard", "takeoff", "land")
ALL_MODES = ev.nav_groups(*ev.NAV_STATE)
PRESENT = ev.health_bits("absolute_pressure", "gps", "accel", "gyro", "magnetometer", "attitude_estimate",
                         "local_position_estimate", "global_position_estimate", "communication_links")


def mavlink_crc32(data: bytes, crc: int = 0) -> int:
    """The CRC32 PX4's generate_component_general.py puts in fileCrc (reflected 0xEDB88320, no
    final xor, starting at 0)."""
    for byte in data:
        crc ^= byte
        for _ in range(8):
            crc = (crc >> 1) ^ (0xEDB88320 if crc & 1 else 0)
    return crc & 0xFFFFFFFF


def metadata_files() -> tuple[dict[str, bytes], int]:
    """(FTP path -> file bytes, CRC of the general metadata JSON) as PX4 serves them."""
    events_json = json.dumps(ev.all_events()).encode()
    general = json.dumps({"version": 1, "metadataTypes": [
        {"type": COMP_METADATA_TYPE_EVENTS, "uri": EVENTS_URI, "fileCrc": mavlink_crc32(events_json),
         "uriFallback": ""},
    ]}).encode()
    files = {
        ftp_path(GENERAL_URI): lzma.compress(general, format=lzma.FORMAT_XZ),
        ftp_path(EVENTS_URI): lzma.compress(events_json, format=lzma.FORMAT_XZ),
    }
    return files, mavlink_crc32(general)


def ftp_path(uri_or_path: str) -> str:
    """`mftp://etc/x` or `/etc/x` -> `etc/x` (PX4 roots FTP paths at its file-system root)."""
    path = uri_or_path.removeprefix("mftp://")
    if path.startswith("[") and "]" in path:  # mftp://[;comp=1]path
        path = path.split("]", 1)[1]
    return path.lstrip("/")


class FtpServer:
    """PX4's MAVLink FTP for read-only files: one session, as mavlink_ftp.cpp allows."""

    def __init__(self, files: dict[str, bytes]) -> None:
        self.files = files
        self.session: tuple[int, bytes] | None = None  # (session id, file bytes)
        self.opened = 0

    def handle(self, payload: bytes) -> list[bytes]:
        """Answers (251-byte payloads) to one request payload."""
        raw = bytes(payload).ljust(251, b"\0")
        seq, session, opcode, size, _, _, _, offset = _HEADER.unpack_from(raw)
        data = raw[12:12 + min(size, DATA_MAX)]
        if opcode == OP_NONE:
            return []
        if opcode == OP_OPEN_RO:
            if self.session is not None:
                return [self._nak(seq, session, opcode, ERR_NO_SESSIONS)]
            content = self.files.get(ftp_path(data.split(b"\0", 1)[0].decode(errors="replace")))
            if content is None:
                return [self._nak(seq, session, opcode, ERR_NOT_FOUND)]
            self.opened += 1
            self.session = (0, content)
            return [self._ack(seq, 0, opcode, 0, struct.pack("<I", len(content)))]
        if opcode in (OP_TERMINATE, OP_RESET):
            self.session = None
            return [self._ack(seq, session, opcode, 0, b"")]
        if opcode in (OP_READ, OP_BURST_READ):
            if self.session is None or session != self.session[0]:
                return [self._nak(seq, session, opcode, ERR_INVALID_SESSION)]
            content = self.session[1]
            if offset >= len(content):
                return [self._nak(seq, session, opcode, ERR_EOF)]
            if opcode == OP_READ:
                return [self._ack(seq, session, opcode, offset, content[offset:offset + DATA_MAX])]
            out = []
            for i in range(BURST_CHUNKS):
                at = offset + i * DATA_MAX
                chunk = content[at:at + DATA_MAX]
                last = i == BURST_CHUNKS - 1 or at + DATA_MAX >= len(content)
                out.append(self._ack(seq + i, session, opcode, at, chunk, burst_complete=last))
                if last:
                    break
            return out
        return [self._nak(seq, session, opcode, ERR_UNKNOWN)]

    @staticmethod
    def _ack(seq: int, session: int, req: int, offset: int, data: bytes, burst_complete: bool = False) -> bytes:
        return (_HEADER.pack((seq + 1) & 0xFFFF, session, OP_ACK, len(data), req, int(burst_complete), 0, offset)
                + data).ljust(251, b"\0")

    @staticmethod
    def _nak(seq: int, session: int, req: int, error: int) -> bytes:
        return _HEADER.pack((seq + 1) & 0xFFFF, session, OP_NAK, 1, req, 0, 0, 0) + bytes([error]) + bytes(238)


class Px4Rules:
    """The PX4 flavour's readiness and metadata rules, driven by `MockAutopilot` hooks."""

    def __init__(self, mock: MockAutopilot, ready_s: float, report_every_s: float | None = None,
                 drift_m: float = DRIFT_XY_M) -> None:
        self.mock = mock
        self.ready_s = ready_s
        self.drift_m = drift_m
        self.drift_dir = np.array([1.0, 0.0, 0.0])  # drawn at each boot (reset)
        # its own generator: the drift's direction leaves the noise's sequence (mock.rng) as it was
        self.drift_rng = np.random.default_rng(mock.config.seed)
        self.origin_sent = False  # GPS_GLOBAL_ORIGIN sent since boot (the origin is new once per boot)
        self.report_every_s = report_every_s
        self.reported_at = -math.inf
        self.reports_due: list[float] = []  # s after boot (reset)
        self.loiter_since: float | None = None  # airborne in AUTO.LOITER after OFFBOARD since (the wander's phase)
        self.offboard_since: float | None = None  # airborne in OFFBOARD since (its wander's phase)
        self.last_mode = ""
        files, self.general_crc = metadata_files()
        self.ftp = FtpServer(files)
        self.ready = True

    # -- hooks -----------------------------------------------------------------------------

    def reset(self) -> None:
        """At boot (and reboot): not ready; home at the local origin until ready."""
        self.ready = self.ready_s <= 0
        self.reported_at = -math.inf
        self.reports_due = [*REPORTS_AT, self.ready_s - ATTITUDE_BEFORE_READY_S]
        self.ftp.session = None
        self.origin_sent = False
        heading = float(self.drift_rng.uniform(0.0, 2.0 * math.pi))
        self.drift_dir = np.array([math.cos(heading), math.sin(heading), 0.0])
        if not self.ready:
            self.mock.home_ned = np.zeros(3)

    @property
    def origin_at(self) -> float:
        """Seconds after boot when the estimator has its global origin (not after it is ready)."""
        return min(ORIGIN_AT_S, self.ready_s)

    def step(self) -> None:
        m = self.mock
        since_boot = m.t - m.boot_t
        due = [t for t in self.reports_due if t <= since_boot]
        if not self.ready and (due or (self.report_every_s is not None
                                       and m.t - self.reported_at >= self.report_every_s)):
            self.reports_due = [t for t in self.reports_due if t > since_boot]
            self.report()  # the checks changed (REPORTS_AT, the attitude valid), or the test's period
        if not self.origin_sent and since_boot >= self.origin_at:
            # the estimator has its global origin: PX4's GPS_GLOBAL_ORIGIN stream sends it once,
            # when it is new (src/modules/mavlink/streams/GPS_GLOBAL_ORIGIN.hpp)
            self.origin_sent = True
            m.log.write("event", m.t, event="px4_origin")
            m._send_stream(mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN, None, requested=True)
        if not self.ready and since_boot >= self.ready_s:
            self.ready = True
            m.home_ned = m.vehicle.state.pos.copy()  # PX4 sets home where the vehicle stands
            m.log.write("event", m.t, event="px4_ready", home=m.home_ned.tolist())
            # HOME_POSITION when home is set (streams/HOME_POSITION.hpp, on home_position updates);
            # the global origin is not new (set at ORIGIN_AT_S): no GPS_GLOBAL_ORIGIN
            m._send_stream(mav.MAVLINK_MSG_ID_HOME_POSITION, None)
            if not m.events:
                m._text(mav.MAV_SEVERITY_INFO, "Ready for takeoff!")
            self.report()

    def sends(self, msg_id: int, requested: bool = False) -> bool:
        """GPS_GLOBAL_ORIGIN only once the estimator has a global origin (the stream sends nothing
        while vehicle_local_position has no xy_global / z_global; measured: 1.4-1.6 s after boot),
        and then only when asked (REQUEST_MESSAGE): the stream sent it once, when it was new
        (`step`), never periodically. ATTITUDE only once its attitude is valid (measured on PX4
        SIH, 5 boots: from 1.1-1.2 s before ready)."""
        since_boot = self.mock.t - self.mock.boot_t
        if msg_id == mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
            return requested and since_boot >= self.origin_at
        if self.ready:
            return True
        if msg_id == mav.MAVLINK_MSG_ID_ATTITUDE:
            return bool(since_boot >= self.ready_s - ATTITUDE_BEFORE_READY_S)
        return True

    def arm_refusal(self) -> str | None:
        """Why PX4 refuses to arm now (None: it may), after saying so as PX4 does."""
        if self.ready:
            return None
        # no report here: the reasons went out when the checks last changed (REPORTS_AT)
        why = "Arming denied: Resolve system health failures first"
        self.mock._report(mav.MAV_SEVERITY_CRITICAL, why, "commander_arm_denied_resolve_failures",
                          internal=mav.MAV_SEVERITY_INFO)
        return why

    def estimate(self, pos: np.ndarray, vel: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """LOCAL_POSITION_NED's position and velocity: before ready, on the ground, the estimate
        drifts away horizontally (DRIFT_XY_M over the time to ready) and its z wanders; at ready
        it is reset to where the vehicle is. In the air, the horizontal estimate wanders in
        OFFBOARD (OFFBOARD_WANDER_*) and in AUTO.LOITER after OFFBOARD (LOITER_WANDER_*), each
        from rest at the mode's start."""
        m = self.mock
        if not self.ready and m.landed:
            since_boot = m.t - m.boot_t
            phase = 2.0 * math.pi * since_boot / DRIFT_PERIOD_S
            frac = since_boot / self.ready_s  # ready_s > 0 here: not ready
            out = pos + self.drift_dir * self.drift_m * frac * frac
            out[2] = m.ground_z + DRIFT_CENTRE + DRIFT_AMPLITUDE * math.sin(phase)
            drift_vel = self.drift_dir * (2.0 * self.drift_m * frac / self.ready_s)
            drift_vel[2] = DRIFT_AMPLITUDE * 2.0 * math.pi / DRIFT_PERIOD_S * math.cos(phase)
            return out, vel + drift_vel
        entered = m.mode != self.last_mode
        if entered:
            self.loiter_since = m.t if m.mode == "LOITER" and self.last_mode == "OFFBOARD" and not m.landed else None
            self.offboard_since = None
            self.last_mode = m.mode
        if m.landed:
            self.offboard_since = None  # the next liftoff starts a wander from rest
            return pos, vel
        if m.mode == "OFFBOARD":
            if self.offboard_since is None:
                self.offboard_since = m.t
            return self._offboard_wander(pos, vel, m.t - self.offboard_since)
        if self.loiter_since is None:
            return pos, vel
        # excursions of 2 r at up to r w: r = M / 2, w = speed / r
        r, rz = LOITER_WANDER_M / 2.0, LOITER_WANDER_Z_M / 2.0
        w, wz = LOITER_WANDER_SPEED / r, LOITER_WANDER_Z_SPEED / rz
        tau = m.t - self.loiter_since
        up = np.array([0.0, 0.0, 1.0])
        return (pos + LOITER_WANDER_DIR * r * (1.0 - math.cos(w * tau)) + up * rz * (1.0 - math.cos(wz * tau)),
                vel + LOITER_WANDER_DIR * LOITER_WANDER_SPEED * math.sin(w * tau)
                + up * LOITER_WANDER_Z_SPEED * math.sin(wz * tau))

    @staticmethod
    def _offboard_wander(pos: np.ndarray, vel: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
        """The estimate in OFFBOARD, `tau` s into the wander (OFFBOARD_WANDER_*): an offset of
        rho = M (1 - cos w tau) / 2 along a direction turning at W."""
        w = 2.0 * math.pi / OFFBOARD_WANDER_PERIOD_S
        turn = 2.0 * math.pi / OFFBOARD_WANDER_TURN_S
        rho = OFFBOARD_WANDER_M * (1.0 - math.cos(w * tau)) / 2.0
        rho_dot = OFFBOARD_WANDER_M * w * math.sin(w * tau) / 2.0
        theta = math.radians(30.0) + turn * tau
        along = np.array([math.cos(theta), math.sin(theta), 0.0])
        across = np.array([-math.sin(theta), math.cos(theta), 0.0])
        return pos + rho * along, vel + rho_dot * along + rho * turn * across

    def component_metadata(self) -> Any:
        return mavwire.component_metadata(self.mock.time_boot_ms, self.general_crc, GENERAL_URI)

    def on_ftp(self, msg: Any) -> None:
        m = self.mock
        if msg.target_system not in (0, m.config.sysid) or msg.target_component not in (0, m.config.compid):
            return
        for payload in self.ftp.handle(bytes(msg.payload)):
            m._send(m.enc.mav.file_transfer_protocol_encode(0, msg.get_srcSystem(), msg.get_srcComponent(),
                                                             list(payload)))

    # -- PX4's arming-check report -----------------------------------------------------------

    def report(self) -> None:
        """Report::report: the summary, each failing check, the health summary (events only;
        PX4 < 1.14 said "Preflight Fail: ..." in STATUSTEXT instead)."""
        m = self.mock
        self.reported_at = m.t
        error = 0 if self.ready else ev.HEALTH_BIT["local_position_estimate"]
        can_arm = ALL_MODES if self.ready else ALL_MODES & ~POSITION_MODES
        if m.events:
            m._report(ev.LEVEL["PROTOCOL"], "Arming check summary event", "commander_arming_check_summary",
                      struct.pack("<BIII", 0, error, 0, can_arm))
        if not self.ready:
            args = ev.arming_check_args(POSITION_MODES, "local_position_estimate")
            # the estimator's check PX4 SIH failed while not ready (measured, 5 boots): vertical velocity
            m._report(mav.MAV_SEVERITY_ERROR, "Preflight Fail: vertical velocity unstable",
                      "check_estimator_vert_vel_not_stable", args)
            m._report(mav.MAV_SEVERITY_ERROR, "Navigation error: No valid position estimate",
                      "check_modes_local_pos", args)
        if m.events:
            m._report(ev.LEVEL["PROTOCOL"], "Health report summary event", "commander_health_summary",
                      struct.pack("<BIII", 0, PRESENT, error, 0))
