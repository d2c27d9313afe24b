"""MockAutopilot: one thread, one select loop, a fixed-rate simulation paced to real time."""

from __future__ import annotations

import math
import select
import struct
import threading
import time
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mav

from . import events as px4_events
from . import px4
from . import telemetry as tm
from .ardupilot import ArduPilotRules
from .control import ControlServer, parse_hostport
from .faults import FaultSpec, LinkFaults
from .log import FlightLog
from .protocol import (
    FORCE_SET_MAGIC,
    Behaviour,
    Flavour,
    ModeTable,
    Param,
    decode_setpoint,
    default_params,
    land_speed,
    target_matches,
)
from .shaping import PX4_LIMIT_PARAMS, px4_vehicle_limits
from .transport import Encoder, Link, parse_endpoint
from .vehicle import DEFAULT_RESPONSE, RESPONSES, Target, Vehicle, VehicleParams

R = mav  # result and enum constants live on the dialect module

# Default stream rates (Hz) of the PX4 flavour, about what PX4 streams on a MAVLink instance in
# Onboard mode (the mode of PX4 SITL's offboard link, udp 14580 -> 14540); SET_MESSAGE_INTERVAL
# changes them. The ArduPilot flavour sends only HEARTBEAT until asked (APM_GROUPS).
DEFAULT_RATES: dict[int, float] = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mav.MAVLINK_MSG_ID_SYS_STATUS: 2.0,
    mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 30.0,
    mav.MAVLINK_MSG_ID_ATTITUDE: 30.0,
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 10.0,
    mav.MAVLINK_MSG_ID_GPS_RAW_INT: 2.0,
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
    mav.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN: 0.1,
    mav.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED: 10.0,
    mav.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
}
# ArduPilot: the legacy stream groups (REQUEST_DATA_STREAM) of the messages the mock sends,
# with the parameter that sets each group's rate at boot. EXTENDED_SYS_STATE, HOME_POSITION
# and SYSTEM_TIME... are in no group here: on request only (SET_MESSAGE_INTERVAL / REQUEST_MESSAGE).
APM_GROUPS: dict[int, tuple[str, tuple[int, ...]]] = {
    mav.MAV_DATA_STREAM_EXTENDED_STATUS: ("MAV1_EXT_STAT", (mav.MAVLINK_MSG_ID_SYS_STATUS, mav.MAVLINK_MSG_ID_GPS_RAW_INT,
                                                            mav.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED)),
    mav.MAV_DATA_STREAM_POSITION: ("MAV1_POSITION", (mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
                                                     mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED)),
    mav.MAV_DATA_STREAM_EXTRA1: ("MAV1_EXTRA1", (mav.MAVLINK_MSG_ID_ATTITUDE,)),
    mav.MAV_DATA_STREAM_EXTRA3: ("MAV1_EXTRA3", (mav.MAVLINK_MSG_ID_SYSTEM_TIME,)),
}
REBOOT_SILENCE_S = 3.0
# The ground's z in the local frame when not configured: PX4's estimator origin sits above the
# ground (z +1.5 to +1.7 m, NED, on a PX4 1.15 SIH SITL's ground); ArduPilot's is on it.
DEFAULT_GROUND_Z = {"px4": 1.6, "ardupilot": 0.0}
# PX4's events enums (arm_disarm_reason_t, failsafe_action_t), for the EVENT arguments.
ARM_REASON = {"command": 4, "auto-disarm after landing": 7, "auto-disarm: no takeoff": 8, "forced": 4,
              "failsafe": 15}
FAILSAFE_ACTION = {"LOITER": 5, "RTL": 6, "LAND": 7, "disarm": 9, "terminate": 10}
STREAM_GAP_S = 0.55  # a 2 Hz stream has 0.5 s gaps; allow a little jitter


@dataclass
class MockConfig:
    autopilot: str = "px4"
    endpoints: list[str] = field(default_factory=lambda: ["udpin:127.0.0.1:14540"])
    sysid: int = 1
    compid: int = 1
    log_path: str | None = None
    speed: float = 1.0
    control: str | None = None
    faults: FaultSpec = field(default_factory=FaultSpec)
    rate_hz: float = 250.0
    log_rate_hz: float | None = None  # None: every simulation step
    home_lat: float = 47.397742
    home_lon: float = 8.545594
    home_alt: float = 488.0
    seed: int | None = None
    wind: tuple[float, float, float] = (0.0, 0.0, 0.0)
    noise: float = 0.0  # std of reported position (m); velocity gets half of it in m/s
    takeovers: list[tuple[float, str]] = field(default_factory=list)
    params: dict[str, float] = field(default_factory=dict)
    offboard_warmup_s: float = 1.0
    # the vehicle's response, one of sitl_mock.vehicle.RESPONSES; None: the flavour's
    # (DEFAULT_RESPONSE: px4 "px4_sih", ardupilot "calibrated")
    vehicle: VehicleParams | None = None
    # MAVLink 2 signing: with a 32-byte key, unsigned or wrongly signed commands and setpoints
    # are ignored (logged as event "signature_rejected"), and everything the mock sends is
    # signed with it (as ArduPilot and PX4 do on a link with signing enabled) unless
    # sign_outgoing is False (an autopilot that checks but signs nothing).
    signing_key: bytes | None = None
    sign_outgoing: bool = True
    # z (NED, m) of the ground in the local frame; None: the flavour's (PX4 +1.6, ArduPilot 0).
    ground_z: float | None = None
    # PX4: report with STATUSTEXT as PX4 < 1.14 did, instead of EVENT messages.
    px4_statustext: bool = False
    # --- ArduPilot strictness and shaping (sitl_mock.ardupilot, sitl_mock.shaping)
    # Throttle pwm the autopilot receives: 1000 is what SITL sends with no transmitter (stick
    # down: pilot modes descend); 1500 mid-stick; None: no RC ever seen.
    rc_throttle: int | None = 1000
    # ArduPilot: seconds after boot until the EKF origin is set (stock SITL: 43 s after its start).
    ekf_origin_delay_s: float = 40.0
    # ArduPilot: seconds after arming before any climb (stock SITL: 3.0 s).
    spool_up_s: float = 3.0
    # Shape targets with the autopilot's own limits (ArduCopter GUIDED: WPNAV_*; PX4: MPC_*).
    shaping: bool = True
    # PX4: seconds from boot until the estimator has settled and arming is allowed (sitl_mock.px4);
    # None: sitl_mock.px4.DEFAULT_READY_S (36.5 s, as PX4 1.15 SIH); 0: ready at boot.
    px4_ready_s: float | None = None

    def validate(self) -> None:
        if self.autopilot not in ("px4", "ardupilot"):
            raise ValueError(f"autopilot: must be 'px4' or 'ardupilot', got {self.autopilot!r}")
        for name in ("sysid", "compid"):
            v = getattr(self, name)
            if not 1 <= v <= 255:
                raise ValueError(f"{name}: must be in 1..255, got {v}")
        if not self.speed > 0:
            raise ValueError(f"speed: must be > 0, got {self.speed}")
        if self.rate_hz < 200:
            raise ValueError(f"rate_hz: must be >= 200, got {self.rate_hz}")
        if not self.endpoints:
            raise ValueError("endpoints: at least one endpoint is needed")
        if self.px4_ready_s is not None and not (math.isfinite(self.px4_ready_s) and self.px4_ready_s >= 0):
            raise ValueError(f"px4_ready_s: must be a finite number of seconds >= 0, got {self.px4_ready_s}")
        if self.ground_z is not None and not (math.isfinite(self.ground_z) and abs(self.ground_z) <= 1000.0):
            raise ValueError(f"ground_z: must be a finite z in [-1000, 1000] m, got {self.ground_z}")
        if self.rc_throttle is not None and not 800 <= self.rc_throttle <= 2200:
            raise ValueError(f"rc_throttle: must be a pwm in 800..2200 or None (no RC), got {self.rc_throttle}")
        for name in ("ekf_origin_delay_s", "spool_up_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name}: must be a finite number of seconds >= 0, got {v}")

    @property
    def resolved_ground_z(self) -> float:
        return DEFAULT_GROUND_Z[self.autopilot] if self.ground_z is None else float(self.ground_z)


class MockAutopilot:
    """A mock PX4 / ArduPilot multicopter speaking MAVLink 2.

    ``start()`` binds the sockets and runs the loop in a background thread; ``stop()``
    ends it and flushes the log. ``run()`` runs the loop in the calling thread.
    """

    def __init__(self, config: MockConfig) -> None:
        config.validate()
        self.config = config
        self.flavour = Flavour(config.autopilot)
        self.modes = ModeTable(self.flavour)
        self.dt = 1.0 / config.rate_hz
        self.ground_z = config.resolved_ground_z
        # home_alt is the ground's altitude (AMSL) at the boot point; the local origin is
        # ground_z above it.
        self.origin = tm.Home(config.home_lat, config.home_lon, config.home_alt + self.ground_z)
        self.events = self.flavour is Flavour.PX4 and not config.px4_statustext
        self.event_seq = 0
        self.params: dict[str, Param] = default_params(self.flavour)
        for name, value in config.params.items():
            if name not in self.params:
                raise ValueError(f"params: unknown parameter {name!r}; known: {sorted(self.params)}")
            self.params[name] = Param(name, float(value), self.params[name].ptype)
        for i, (_, mode) in enumerate(config.takeovers):
            try:
                self.modes.canonical(mode)
            except ValueError as exc:
                raise ValueError(f"takeovers[{i}]: {exc}") from None
        response = config.vehicle if config.vehicle is not None else RESPONSES[DEFAULT_RESPONSE[config.autopilot]]
        self.vehicle = Vehicle(response, ground_z=self.ground_z)
        self.enc = Encoder(config.sysid, config.compid)
        if config.signing_key is not None and config.sign_outgoing:
            signing = self.enc.mav.signing
            signing.secret_key, signing.sign_outgoing, signing.link_id = config.signing_key, True, 0
            # 10 µs units since 2015-01-01 (the MAVLink signing epoch), from the wall clock
            signing.timestamp = int(max(time.time() - 1420070400, 0.0) * 100_000)
        self.log = FlightLog(config.log_path)
        self.link_faults = LinkFaults(config.faults, config.seed)
        self.reject_arming = config.faults.reject_arming
        self.rng = np.random.default_rng(config.seed)
        self.wind = np.asarray(config.wind, dtype=float)
        self.links: list[Link] = []
        self.control: ControlServer | None = None
        self._thread: threading.Thread | None = None
        self._stop = threading.Event()
        self._lock = threading.Lock()  # guards the state snapshot read by other threads
        self._schedule: list[tuple[float, str, Any]] = sorted(
            [(at, "pause", dur) for at, dur in config.faults.pauses]
            + [(at, "reboot", None) for at in config.faults.reboots]
            + [(at, "takeover", mode) for at, mode in config.takeovers],
            key=lambda e: e[0],
        )
        self.t = 0.0
        self._step_count = 0
        self._log_every = max(1, round(config.rate_hz / config.log_rate_hz)) if config.log_rate_hz else 1
        self._snapshot: dict[str, Any] = {}
        self._last_reject_text: dict[str, float] = {}
        self._reboot_pending = False
        self.ap = ArduPilotRules(config.rc_throttle, config.ekf_origin_delay_s, config.spool_up_s, config.shaping)
        # PX4 readiness, component metadata and FTP (sitl_mock.px4); None for ArduPilot.
        ready_s = px4.DEFAULT_READY_S if config.px4_ready_s is None else config.px4_ready_s
        self.px4 = px4.Px4Rules(self, ready_s) if self.flavour is Flavour.PX4 else None
        self._reset_state()

    # ------------------------------------------------------------------ lifecycle

    def bind(self) -> None:
        if self.links:
            return
        self.links = [Link(parse_endpoint(e)) for e in self.config.endpoints]
        for link in self.links:
            link.signing_key = self.config.signing_key
        if self.config.control:
            host, port = parse_hostport(self.config.control, "control")
            self.control = ControlServer(host, port, self._control_request)

    @property
    def addresses(self) -> list[tuple[str, int]]:
        """Bound (host, port) of each endpoint, useful when port 0 was asked for."""
        return [link.address for link in self.links]

    @property
    def control_address(self) -> tuple[str, int] | None:
        return self.control.address if self.control else None

    def start(self) -> MockAutopilot:
        self.bind()
        self._thread = threading.Thread(target=self.run, name="sitl-mock", daemon=True)
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(timeout=5.0)
        self._close()

    def request_stop(self) -> None:
        self._stop.set()

    def __enter__(self) -> MockAutopilot:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()

    def _close(self) -> None:
        for link in self.links:
            link.close()
        if self.control:
            self.control.close()
        self.log.close()

    def snapshot(self) -> dict[str, Any]:
        """Thread-safe copy of the vehicle state (as the control socket's ``state``)."""
        with self._lock:
            return dict(self._snapshot)

    # ------------------------------------------------------------------ state

    def _reset_state(self) -> None:
        self.boot_t = self.t
        self.mode = self.modes.boot_mode  # the mode in force (PX4's nav_state), as reported
        # PX4's UserModeIntention: the mode the user asked for (a failsafe overrides it while
        # active) and the one to go back to on disarm (never one that prevents arming).
        self.user_mode = self.mode
        self.mode_after_disarm = self.mode
        self.failsafe_mode: str | None = None
        self.armed = False
        self.vehicle.reset()
        # Home: the boot point on the ground; PX4 moves it to where it arms.
        self.home_ned = np.array([0.0, 0.0, self.ground_z])
        self.hold_target = Target.hold(self.home_ned, 0.0)
        self.follow_target: Target | None = None
        self.sp_times: list[float] = []
        self.stream_start = -math.inf
        self.last_sp = -math.inf
        self.arm_t = -math.inf
        self.airborne_since_arm = False
        self.landed_since = self.t
        self.guided_taken_off = False
        self.takeoff_alt = float(self.params["MIS_TAKEOFF_ALT"].value) if self.flavour is Flavour.PX4 else 0.0
        self.takeoff_xy = np.zeros(2)
        self.rtl_landing = False
        self.rebooting_until = -math.inf
        self.ap.reset()
        self.next_due = {mid: self.t for mid in DEFAULT_RATES}
        if self.px4 is not None:
            self.px4.reset()
        self.intervals = {mid: 1.0 / hz for mid, hz in DEFAULT_RATES.items()}
        if self.flavour is Flavour.ARDUPILOT:
            # Stock ArduPilot on a fresh link: HEARTBEAT only (and STATUSTEXT as it happens),
            # plus the groups whose MAV1_* rate parameter is set.
            for mid in self.intervals:
                if mid != mav.MAVLINK_MSG_ID_HEARTBEAT:
                    self.intervals[mid] = math.inf
            for group in APM_GROUPS:
                self._set_group(group, self._param(APM_GROUPS[group][0]))
        self._update_snapshot()

    def _param(self, name: str) -> float:
        return float(self.params[name].value)

    @property
    def time_boot_ms(self) -> int:
        return int((self.t - self.boot_t) * 1000) & 0xFFFFFFFF

    @property
    def landed(self) -> bool:
        return self.vehicle.state.on_ground

    def stream_ok(self) -> bool:
        """PX4 proof of life: valid setpoints at >= 2 Hz for at least the warm-up time.

        PX4's docs ask for a stream older than one second; its code (offboardCheck.cpp)
        only asks for one setpoint within COM_OF_LOSS_T, which ``offboard_warmup_s = 0``
        reproduces.
        """
        warmup = self.config.offboard_warmup_s
        if warmup <= 0:
            return self.t - self.last_sp <= self._param("COM_OF_LOSS_T")
        return self.t - self.last_sp <= STREAM_GAP_S and self.t - self.stream_start >= warmup

    def _update_snapshot(self) -> None:
        s = self.vehicle.state
        with self._lock:
            self._snapshot = {
                "t": self.t,
                "position": s.pos.tolist(),
                "velocity": s.vel.tolist(),
                "yaw": s.yaw,
                "mode": self.mode,
                "armed": self.armed,
                "landed": self.landed,
                "link_paused": self.link_faults.paused(self.t),
                "rebooting": self.t < self.rebooting_until,
                "user_mode": self.user_mode,
                "failsafe": self.failsafe_mode is not None,
                "ground_z": self.ground_z,
                "home": self.home_ned.tolist(),
                "ekf_origin": self.flavour is Flavour.PX4 or self.ap.origin_set,
                "rc_failsafe": self.ap.radio_failsafe,
                # PX4: the estimator has settled and arming is allowed (sitl_mock.px4)
                "ready": self.px4.ready if self.px4 is not None else True,
            }

    # ------------------------------------------------------------------ loop

    def run(self) -> None:
        self.bind()
        speed = self.config.speed
        wall0 = time.monotonic()
        max_catchup = max(10, int(0.25 * self.config.rate_hz))
        try:
            while not self._stop.is_set():
                sim_now = (time.monotonic() - wall0) * speed
                n = 0
                while self.t + self.dt <= sim_now and n < max_catchup:
                    self._step()
                    n += 1
                if n == max_catchup:
                    # Too slow to keep up: let simulated time slip rather than spiral.
                    wall0 = time.monotonic() - self.t / speed
                self._release_delayed()
                deadline = wall0 + (self.t + self.dt) / speed
                nxt = self.link_faults.next_release()
                if nxt is not None:
                    deadline = min(deadline, wall0 + nxt / speed)
                timeout = max(0.0, deadline - time.monotonic())
                socks = [s for link in self.links for s in link.poll_sockets()]
                if self.control:
                    socks += self.control.sockets()
                try:
                    readable, _, _ = select.select(socks, [], [], timeout)
                except (OSError, ValueError):
                    readable = []
                for sock in readable:
                    self._on_readable(sock)
        finally:
            self.log.write("event", self.t, event="stopped")
            self.log.flush()

    def _on_readable(self, sock: Any) -> None:
        if self.control and sock in self.control.sockets():
            self.control.handle_readable(sock)
            return
        for link in self.links:
            if sock in link.poll_sockets():
                for peer, data in link.read(sock):
                    if self.t < self.rebooting_until or not self.link_faults.admit(self.t, "in"):
                        continue
                    if self.link_faults.latency_s > 0:
                        self.link_faults.push(self.t, ("in", link, peer, data))
                    else:
                        self._on_data(link, peer, data)
                return

    def _release_delayed(self) -> None:
        for item in self.link_faults.due(self.t):
            if item[0] == "in":
                _, link, peer, data = item
                self._on_data(link, peer, data)
            else:
                for link in self.links:
                    link.send(item[1])

    def _on_data(self, link: Link, peer: Any, data: bytes) -> None:
        rejected = link.rejected
        for msg in link.parse(peer, data):
            self._on_message(msg)
        if link.rejected > rejected:
            self.log.write("event", self.t, event="signature_rejected", count=link.rejected - rejected,
                           total=link.rejected)

    def _send(self, msg: Any) -> None:
        if self.t < self.rebooting_until or not self.link_faults.admit(self.t, "out"):
            return
        data = self.enc.encode(msg)
        if self.link_faults.latency_s > 0:
            self.link_faults.push(self.t, ("out", data))
            return
        for link in self.links:
            link.send(data)

    def _text(self, severity: int, text: str) -> None:
        self.log.write("event", self.t, event="statustext", severity=severity, text=text)
        self._send(tm.statustext(self.enc.mav, severity, text))

    def _report(self, severity: int, text: str, event: str | None, args: bytes = b"",
                internal: int | None = None) -> None:
        """What an autopilot tells the ground: PX4 >= 1.14 an EVENT (none if `event` is None,
        as PX4 reports plain mode changes and rejected setpoints on its console only), else
        STATUSTEXT. `severity` is the external log level (MAV_SEVERITY numbering)."""
        if not self.events:
            self._text(severity, text)
            return
        if event is None:
            return
        seq = self.event_seq
        self.event_seq = (self.event_seq + 1) & 0xFFFF
        self.log.write("event", self.t, event="px4_event", name=event, id=px4_events.IDS[event],
                       level=px4_events.LEVELS[severity], sequence=seq, text=text)
        self._send(tm.event(self.enc.mav, event, severity, seq, self.time_boot_ms, args, internal))

    # ------------------------------------------------------------------ simulation step

    def _step(self) -> None:
        # t from a step count, not a running sum, so that timings in the log do not drift.
        self._step_count += 1
        self.t = self._step_count * self.dt
        while self._schedule and self._schedule[0][0] <= self.t:
            _, kind, arg = self._schedule.pop(0)
            self._scheduled(kind, arg)
        if self.t < self.rebooting_until:
            self._update_snapshot()
            return
        self._rules()
        if self.px4 is not None:
            self.px4.step()
        target = self._target()
        self.vehicle.step(self.dt, target, self.armed, self.wind)
        self._after_physics()
        self._telemetry(target)
        if self._step_count % self._log_every == 0:
            s = self.vehicle.state
            self.log.write(
                "state", self.t, pos=s.pos.tolist(), vel=s.vel.tolist(), acc=s.acc.tolist(),
                yaw=s.yaw, mode=self.mode, armed=self.armed, landed=self.landed,
            )
        self._update_snapshot()

    def _scheduled(self, kind: str, arg: Any) -> None:
        if kind == "pause":
            self.pause_link(float(arg))
        elif kind == "reboot":
            self.reboot()
        elif kind == "takeover":
            ok, why = self.pilot_set_mode(str(arg))
            if not ok:
                self.log.write("event", self.t, event="takeover_refused", mode=arg, reason=why)

    def _rules(self) -> None:
        """Autopilot-side decisions that depend on time: failsafes, timeouts, auto-disarm."""
        if self.flavour is Flavour.ARDUPILOT:
            self.ap.tick(self)  # EKF origin, RC failsafe (sitl_mock.ardupilot)
        if (self.flavour is Flavour.PX4 and self.armed and self.user_mode == "OFFBOARD"
                and self.failsafe_mode is None):
            loss_t = self._param("COM_OF_LOSS_T")
            if self.t - self.last_sp > loss_t:
                self._offboard_failsafe()
        if (
            self.flavour is Flavour.ARDUPILOT
            and self.mode == "GUIDED"
            and self.follow_target is not None
            and self.t - self.last_sp > self._param("GUID_TIMEOUT")
        ):
            ft = self.follow_target
            if np.any(np.isfinite(ft.vel) & (ft.vel != 0)) or np.any(np.isfinite(ft.acc) & (ft.acc != 0)):
                # ArduPilot zeroes the velocity/acceleration feed-forward, keeps the position.
                ft.vel = np.where(np.isfinite(ft.vel), 0.0, ft.vel)
                ft.acc = np.where(np.isfinite(ft.acc), 0.0, ft.acc)
                if not np.any(np.isfinite(ft.pos)):
                    ft.vel = np.zeros(3)
                self.log.write("event", self.t, event="guided_timeout")

    def _offboard_failsafe(self) -> None:
        """PX4's mode fallback for a lost offboard signal (failsafe.cpp checkModeFallback).

        COM_OBL_RC_ACT 0-2 fall back to Position, Altitude or Stabilized mode, which need RC;
        the mock has none, so the fallback chain ends in Return, as PX4's does. OFFBOARD stays
        the user's mode: a setpoint arriving while armed ends the failsafe (`_on_setpoint`).
        """
        action = int(self._param("COM_OBL_RC_ACT"))
        target = {3: "RTL", 4: "LAND", 5: "LOITER", 6: "terminate", 7: "disarm"}.get(action, "RTL")
        self.log.write("event", self.t, event="failsafe", cause="offboard_loss",
                       last_setpoint_t=self.last_sp, action=target)
        args = struct.pack("<IB", self.modes.custom_mode(self.user_mode), FAILSAFE_ACTION[target])
        self._report(mav.MAV_SEVERITY_CRITICAL, "Failsafe activated: no offboard signal",
                     "commander_failsafe_enter_generic", args, internal=mav.MAV_SEVERITY_WARNING)
        if target in ("terminate", "disarm"):
            self._disarm("failsafe")
            return
        self.failsafe_mode = target
        self._set_mode(target, "failsafe")

    def _clear_failsafe(self, reason: str) -> None:
        self.failsafe_mode = None
        self.log.write("event", self.t, event="failsafe_cleared", reason=reason, mode=self.user_mode)
        self._set_mode(self.user_mode, reason)

    def _after_physics(self) -> None:
        s = self.vehicle.state
        if not self.armed:
            self.landed_since = self.t if not self.landed else self.landed_since
            return
        if not self.landed:
            if self.landed_since != math.inf and self.flavour is Flavour.PX4:
                self._report(mav.MAV_SEVERITY_INFO, "Takeoff detected", "commander_takeoff_detected")
            self.airborne_since_arm = True
            self.landed_since = math.inf
            return
        if self.landed_since == math.inf:
            self.landed_since = self.t
            if self.airborne_since_arm:
                self.log.write("event", self.t, event="landed", pos=s.pos.tolist())
                if self.flavour is Flavour.PX4:
                    self._report(mav.MAV_SEVERITY_INFO, "Landing detected", "commander_landing_detected")
        landed_for = self.t - self.landed_since
        behaviour = self.modes.behaviour(self.mode)
        if self.airborne_since_arm:
            if self.flavour is Flavour.PX4:
                limit = self._param("COM_DISARM_LAND")
            else:
                limit = 1.0 if behaviour in (Behaviour.LAND, Behaviour.RTL) else self._param("DISARM_DELAY")
            if limit > 0 and landed_for >= limit:
                self._disarm("auto-disarm after landing")
            return
        if self.flavour is Flavour.ARDUPILOT and self.guided_taken_off:
            return  # takeoff in progress: motors spooling up
        limit = self._param("COM_DISARM_PRFLT") if self.flavour is Flavour.PX4 else self._param("DISARM_DELAY")
        if limit > 0 and self.t - self.arm_t >= limit and landed_for >= limit:
            self._disarm("auto-disarm: no takeoff")

    def _target(self) -> Target | None:
        # --- flavour hooks: ArduPilot's modes and GUIDED shaping (sitl_mock.ardupilot); PX4's
        # MPC_* velocity and tilt limits (sitl_mock.shaping)
        if self.flavour is Flavour.ARDUPILOT:
            return self.ap.target(self)
        if self.config.shaping:
            self.vehicle.limits = px4_vehicle_limits({n: float(self.params[n].value) for n in PX4_LIMIT_PARAMS})
        return self._base_target()

    def _base_target(self) -> Target | None:
        if not self.armed:
            return None
        s = self.vehicle.state
        behaviour = self.modes.behaviour(self.mode)
        if behaviour is Behaviour.FOLLOW:
            if self.flavour is Flavour.ARDUPILOT and self.landed and not self.guided_taken_off:
                return Target.hold(np.array([s.pos[0], s.pos[1], self.ground_z]), s.yaw)
            return self.follow_target if self.follow_target is not None else self.hold_target
        if behaviour is Behaviour.TAKEOFF:
            goal = np.array([self.takeoff_xy[0], self.takeoff_xy[1], self.home_ned[2] - self.takeoff_alt])
            if abs(s.pos[2] - goal[2]) < 0.1 and abs(s.vel[2]) < 0.3:
                self._user_mode("LOITER", "takeoff complete")
                return self.hold_target
            return Target.hold(goal, s.yaw)
        if behaviour is Behaviour.LAND:
            return self._land_target()
        if behaviour is Behaviour.RTL:
            home = self.home_ned
            if not self.rtl_landing and float(np.hypot(s.pos[0] - home[0], s.pos[1] - home[1])) < 0.5:
                self.rtl_landing = True
                self.takeoff_xy = home[:2].copy()
                self.hold_target = Target.hold(np.array([home[0], home[1], s.pos[2]]), s.yaw)
            if self.rtl_landing:
                return self._land_target()
            return Target.hold(np.array([home[0], home[1], min(s.pos[2], self.hold_target.pos[2])]), s.yaw)
        return self.hold_target

    def _land_target(self) -> Target:
        xy = self.hold_target.pos[:2]
        pos = np.array([xy[0], xy[1], np.nan])
        vel = np.array([0.0, 0.0, land_speed(self.flavour, self.params)])
        return Target(pos, vel, np.zeros(3), math.nan, math.nan)

    # ------------------------------------------------------------------ modes, arming

    def _set_mode(self, name: str, reason: str) -> None:
        if name == self.mode:
            return
        old = self.mode
        self.mode = name
        s = self.vehicle.state
        self.hold_target = Target.hold(s.pos.copy(), s.yaw)
        if self.landed:
            self.hold_target.pos[2] = min(s.pos[2], self.ground_z)
        self.rtl_landing = False
        self.ap.on_mode()
        if name == self.modes.follow_mode:
            # PX4 publishes trajectory setpoints only once in OFFBOARD, so it starts from
            # a hold until the next setpoint; GUIDED starts by holding too.
            self.follow_target = None
        if self.modes.behaviour(name) is Behaviour.TAKEOFF:
            self.takeoff_xy = s.pos[:2].copy()
        self.log.write("mode", self.t, **{"from": old, "to": name, "reason": reason})
        self._report(mav.MAV_SEVERITY_INFO, f"Mode {old} -> {name} ({reason})"[:50], None)
        self._send_heartbeat()

    def _user_mode(self, name: str, reason: str) -> None:
        """The user's (or navigator's) mode change: it also ends a failsafe."""
        self.user_mode = name
        if not self.modes.prevents_arming(name) and self.modes.behaviour(name) is not Behaviour.TAKEOFF:
            self.mode_after_disarm = name
        self.failsafe_mode = None
        self._set_mode(name, reason)

    def request_mode(self, name: str, source: str) -> tuple[int, str]:
        """A mode change asked for over MAVLink or by the pilot; returns (MAV_RESULT, why)."""
        if self.flavour is Flavour.PX4 and name == "OFFBOARD" and not self.stream_ok():
            why = "Switching to Offboard denied: no offboard signal"
            args = struct.pack("<IB", self.modes.custom_mode(name), px4_events.NAV_MODE[name])  # navigation_mode_t
            self._report(mav.MAV_SEVERITY_CRITICAL, why, "commander_modeswitch_not_avail", args,
                         internal=mav.MAV_SEVERITY_INFO)
            self._report(mav.MAV_SEVERITY_ERROR, "No offboard signal", "check_modes_offboard_no_signal")
            self.log.write("event", self.t, event="mode_refused", mode=name, source=source, reason=why)
            return int(mav.MAV_RESULT_TEMPORARILY_REJECTED), why
        self._user_mode(name, source)
        return int(mav.MAV_RESULT_ACCEPTED), ""

    def pilot_set_mode(self, mode: str) -> tuple[bool, str]:
        name = self.modes.canonical(mode)
        result, why = self.request_mode(name, "pilot")
        return result == mav.MAV_RESULT_ACCEPTED, why

    def _refuse(self) -> int:
        return int(mav.MAV_RESULT_DENIED if self.flavour is Flavour.PX4 else mav.MAV_RESULT_FAILED)

    def _refuse_arming(self) -> int:
        """PX4 answers a denied arm/disarm transition with TEMPORARILY_REJECTED."""
        return int(mav.MAV_RESULT_TEMPORARILY_REJECTED if self.flavour is Flavour.PX4 else mav.MAV_RESULT_FAILED)

    def arm(self, force: bool) -> tuple[int, str]:
        if self.armed:
            return int(mav.MAV_RESULT_ACCEPTED), ""
        why, event = "", ""
        if self.px4 is not None and not force:
            refusal = self.px4.arm_refusal()  # PX4 has said why in its own events
            if refusal:
                self.log.write("event", self.t, event="arming_refused", reason=refusal)
                return self._refuse_arming(), refusal
        if self.reject_arming:
            why, event = "Arming denied: preflight checks failed", "check_rc_dl_no_dllink"
        elif self.flavour is Flavour.PX4 and self.mode == "OFFBOARD" and not self.stream_ok():
            why, event = "Arming denied: no offboard signal", "check_modes_offboard_no_signal"
        elif self.modes.prevents_arming(self.mode) and not force:
            why, event = f"Arming denied: not armable in {self.mode}", "mock_arm_denied_mode"
        elif self.flavour is Flavour.ARDUPILOT and not force and (fails := self.ap.prearm_failures(self)):
            for text in fails[1:]:  # ArduPilot reports every failing check
                self._text(mav.MAV_SEVERITY_CRITICAL, text)
            why, event = fails[0], ""
        if why:
            # PX4's arming checks report as errors; the old STATUSTEXT was critical.
            self._report(mav.MAV_SEVERITY_ERROR if self.events else mav.MAV_SEVERITY_CRITICAL, why, event)
            self.log.write("event", self.t, event="arming_refused", reason=why)
            return self._refuse_arming() if self.flavour is Flavour.PX4 else self._refuse(), why
        self.armed = True
        self.arm_t = self.t
        self.airborne_since_arm = False
        self.guided_taken_off = False
        self.landed_since = self.t
        s = self.vehicle.state
        self.hold_target = Target.hold(s.pos.copy(), s.yaw)
        self.log.write("event", self.t, event="armed", mode=self.mode)
        self._report(mav.MAV_SEVERITY_INFO, "Armed", "commander_armed_by", bytes([ARM_REASON["command"]]))
        if self.flavour is Flavour.PX4:
            # PX4 (COM_HOME_EN) sets home where it arms, and streams the new home at once.
            self.home_ned = s.pos.copy()
            self._send(tm.home_position(self.enc.mav, self.origin, self.home_ned, int((self.t - self.boot_t) * 1e6)))
        else:
            self.ap.on_armed(self)  # ArduPilot: home where it arms, sent at once
        self._send_heartbeat()
        return int(mav.MAV_RESULT_ACCEPTED), ""

    def _disarm(self, reason: str) -> None:
        self.armed = False
        self.guided_taken_off = False
        self.log.write("event", self.t, event="disarmed", reason=reason)
        self._report(mav.MAV_SEVERITY_INFO, f"Disarmed: {reason}"[:50], "commander_disarmed_by",
                     bytes([ARM_REASON.get(reason, ARM_REASON["command"])]))
        if self.flavour is Flavour.PX4:
            # PX4 ends any failsafe and goes back to the last user mode one can arm in.
            self.failsafe_mode = None
            self.user_mode = self.mode_after_disarm
            self._set_mode(self.user_mode, "disarmed")
        self._send_heartbeat()

    def disarm(self, force: bool) -> tuple[int, str]:
        if not self.armed:
            return int(mav.MAV_RESULT_ACCEPTED), ""
        if not self.landed and not force:
            why = "Disarming denied: not landed"
            self._report(mav.MAV_SEVERITY_CRITICAL, why, "commander_disarm_denied_not_landed",
                         internal=mav.MAV_SEVERITY_INFO)
            return self._refuse_arming(), why
        self._disarm("command" if not force else "forced")
        return int(mav.MAV_RESULT_ACCEPTED), ""

    def takeoff(self, param7: float) -> tuple[int, str]:
        s = self.vehicle.state
        if self.flavour is Flavour.PX4:
            # PX4's param7 is an AMSL altitude; NaN means MIS_TAKEOFF_ALT above home.
            home_amsl = self.origin.alt - float(self.home_ned[2])
            alt = param7 - home_amsl if math.isfinite(param7) else self._param("MIS_TAKEOFF_ALT")
            if alt <= 0.0:
                why = "takeoff altitude below home"
                self._report(mav.MAV_SEVERITY_CRITICAL, why, "mock_takeoff_denied_alt")
                return int(mav.MAV_RESULT_DENIED), why
            if not math.isfinite(param7):
                self._report(mav.MAV_SEVERITY_INFO, f"Using default takeoff altitude: {alt:.1f} m",
                             "navigator_takeoff_default_alt", struct.pack("<f", alt))
            self.takeoff_alt = alt
            self._user_mode("TAKEOFF", "takeoff command")
            return int(mav.MAV_RESULT_ACCEPTED), ""
        why = ""
        if self.mode != "GUIDED":
            why = f"Takeoff refused: mode {self.mode} is not GUIDED"
        elif not self.armed:
            why = "Takeoff refused: not armed"
        elif not self.landed or self.guided_taken_off:
            why = "Takeoff refused: already flying"
        elif not (math.isfinite(param7) and param7 > 0):
            why = "Takeoff refused: altitude must be > 0"
        if why:
            self._report(mav.MAV_SEVERITY_WARNING, why, None)
            self.log.write("event", self.t, event="takeoff_refused", reason=why)
            return int(mav.MAV_RESULT_FAILED), why
        self.guided_taken_off = True
        self.takeoff_alt = param7
        self.follow_target = Target.hold(np.array([s.pos[0], s.pos[1], self.home_ned[2] - param7]), s.yaw)
        self.log.write("event", self.t, event="takeoff", alt=param7)
        return int(mav.MAV_RESULT_ACCEPTED), ""

    def pause_link(self, seconds: float) -> None:
        self.link_faults.pause(self.t, seconds)
        self.log.write("event", self.t, event="link_paused", seconds=seconds)

    def reboot(self) -> None:
        self.log.write("event", self.t, event="reboot")
        self.link_faults.clear()
        self._reset_state()
        self.rebooting_until = self.t + REBOOT_SILENCE_S
        self.boot_t = self.rebooting_until  # the clock restarts when it has booted
        for mid in self.next_due:
            self.next_due[mid] = self.rebooting_until
        self.log.write("mode", self.t, **{"from": None, "to": self.mode, "reason": "reboot"})
        self._update_snapshot()

    # ------------------------------------------------------------------ incoming MAVLink

    def _on_message(self, msg: Any) -> None:
        kind = msg.get_type()
        handler = {
            "COMMAND_LONG": self._on_command_long,
            "COMMAND_INT": self._on_command_int,
            "SET_MODE": self._on_set_mode,
            "SET_POSITION_TARGET_LOCAL_NED": self._on_setpoint,
            "PARAM_REQUEST_LIST": self._on_param_list,
            "PARAM_REQUEST_READ": self._on_param_read,
            "PARAM_SET": self._on_param_set,
            "MISSION_REQUEST_LIST": self._on_mission_list,
            "TIMESYNC": self._on_timesync,
            "REQUEST_DATA_STREAM": self._on_request_data_stream,
            "FILE_TRANSFER_PROTOCOL": self.px4.on_ftp if self.px4 is not None else None,
        }.get(kind)
        if handler is None:
            return
        try:
            handler(msg)
        except Exception as exc:  # a malformed packet must not take the autopilot down
            self.log.write("event", self.t, event="handler_error", message=kind, error=repr(exc))
        self._update_snapshot()

    def _for_us(self, msg: Any) -> bool:
        return target_matches(msg.target_system, msg.target_component, self.config.sysid, self.config.compid)

    def _on_command_long(self, msg: Any) -> None:
        if not self._for_us(msg):
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        self._command(msg, int(msg.command), params)

    def _on_command_int(self, msg: Any) -> None:
        if not self._for_us(msg):
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        self._command(msg, int(msg.command), params)

    def _command(self, msg: Any, command: int, p: tuple[float, ...]) -> None:
        result, why = self._dispatch_command(command, p)
        self.log.write("event", self.t, event="command", command=command, params=list(p),
                       result=result, reason=why)
        self._update_snapshot()  # so that whoever sees the ACK sees its effect too
        self._send(self.enc.mav.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(),
                                                   msg.get_srcComponent()))
        if self._reboot_pending:
            self._reboot_pending = False
            self.reboot()

    def _dispatch_command(self, command: int, p: tuple[float, ...]) -> tuple[int, str]:
        if command == mav.MAV_CMD_COMPONENT_ARM_DISARM:
            force = _int(p[1]) == FORCE_SET_MAGIC
            return self.arm(force) if p[0] >= 0.5 else self.disarm(force)
        if command == mav.MAV_CMD_DO_SET_MODE:
            return self._do_set_mode(_int(p[0]), _int(p[1]), _int(p[2]))
        if command == mav.MAV_CMD_NAV_TAKEOFF:
            return self.takeoff(float(p[6]))
        if command == mav.MAV_CMD_NAV_LAND:
            return self.request_mode("LAND", "land command")
        if command == mav.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self.request_mode(self.modes.canonical("RTL"), "rtl command")
        if command == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(_int(p[0]), float(p[1]))
        if command == mav.MAV_CMD_REQUEST_MESSAGE:
            return self._request_message(_int(p[0]))
        if command == mav.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN and _int(p[0]) == 1:
            if self.armed:
                return self._refuse(), "reboot refused: armed"
            # Acknowledged first, as the autopilot does before it goes quiet.
            self._reboot_pending = True
            return int(mav.MAV_RESULT_ACCEPTED), ""
        if command == mav.MAV_CMD_GET_HOME_POSITION:  # deprecated for REQUEST_MESSAGE, still answered
            return self._request_message(mav.MAVLINK_MSG_ID_HOME_POSITION)
        if command == mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return self._request_message(mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        return int(mav.MAV_RESULT_UNSUPPORTED), f"command {command} unsupported"

    def _do_set_mode(self, base: int, main: int, sub: int) -> tuple[int, str]:
        if not base & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return int(mav.MAV_RESULT_UNSUPPORTED), "base mode without custom mode flag"
        name = self.modes.from_custom(main, sub)
        if name is None:
            why = f"unknown custom mode {main}/{sub}"
            self._report(mav.MAV_SEVERITY_WARNING, why, None)
            return self._refuse(), why
        result, why = self.request_mode(name, "command")
        if result != mav.MAV_RESULT_ACCEPTED and self.flavour is Flavour.ARDUPILOT:
            result = int(mav.MAV_RESULT_FAILED)
        return result, why

    def _on_set_mode(self, msg: Any) -> None:
        if msg.target_system not in (0, self.config.sysid):
            return
        result, _ = self._do_set_mode(int(msg.base_mode), *self._split_custom(int(msg.custom_mode)))
        # PX4 acks a SET_MODE as the DO_SET_MODE it turns it into; ArduPilot acks message id 11.
        command = mav.MAV_CMD_DO_SET_MODE if self.flavour is Flavour.PX4 else mav.MAVLINK_MSG_ID_SET_MODE
        self._update_snapshot()
        self._send(self.enc.mav.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(),
                                                   msg.get_srcComponent()))

    def _split_custom(self, custom_mode: int) -> tuple[int, int]:
        if self.flavour is Flavour.PX4:
            return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
        return custom_mode, 0

    def _set_interval(self, msg_id: int, interval_us: float) -> tuple[int, str]:
        if msg_id not in DEFAULT_RATES:
            return int(mav.MAV_RESULT_DENIED), f"message {msg_id} cannot be streamed"
        if interval_us < 0:
            self.intervals[msg_id] = math.inf
        elif interval_us == 0:  # the default rate: ArduPilot's stock one is "not streamed"
            self.intervals[msg_id] = 1.0 / DEFAULT_RATES[msg_id] if self.flavour is Flavour.PX4 else math.inf
        else:
            self.intervals[msg_id] = max(interval_us * 1e-6, self.dt)
        self.next_due[msg_id] = self.t
        return int(mav.MAV_RESULT_ACCEPTED), ""

    def _set_group(self, group: int, hz: float) -> None:
        """ArduPilot: one legacy stream group at `hz` (0: stopped)."""
        groups = list(APM_GROUPS) if group == mav.MAV_DATA_STREAM_ALL else [group]
        for g in groups:
            if g not in APM_GROUPS:
                continue
            for mid in APM_GROUPS[g][1]:
                self.intervals[mid] = max(1.0 / hz, self.dt) if hz > 0 else math.inf
                self.next_due[mid] = self.t

    def _on_request_data_stream(self, msg: Any) -> None:
        if self.flavour is not Flavour.ARDUPILOT or not self._for_us(msg):
            return  # PX4 ignores the legacy request
        hz = float(msg.req_message_rate) if msg.start_stop else 0.0
        self._set_group(int(msg.req_stream_id), hz)
        self.log.write("event", self.t, event="request_data_stream", stream=int(msg.req_stream_id), rate_hz=hz)

    def _request_message(self, msg_id: int) -> tuple[int, str]:
        if msg_id == mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            self._send(tm.autopilot_version(self.enc.mav, self.flavour, self.config.sysid))
        elif msg_id == px4.MSG_ID_COMPONENT_METADATA and self.px4 is not None:
            self._send(self.px4.component_metadata())
        elif msg_id in DEFAULT_RATES:
            self._send_stream(msg_id, self._target())
        else:
            return int(mav.MAV_RESULT_UNSUPPORTED), f"message {msg_id} not available"
        return int(mav.MAV_RESULT_ACCEPTED), ""

    def _on_setpoint(self, msg: Any) -> None:
        s = self.vehicle.state
        record: dict[str, Any] = {
            "frame": int(msg.coordinate_frame), "type_mask": int(msg.type_mask),
            "target_system": int(msg.target_system), "target_component": int(msg.target_component),
            "raw_pos": [msg.x, msg.y, msg.z], "raw_vel": [msg.vx, msg.vy, msg.vz],
            "raw_acc": [msg.afx, msg.afy, msg.afz], "yaw": msg.yaw, "yaw_rate": msg.yaw_rate,
            # the sender's clock: gaps in it are the sender's, not this loop's scheduling
            "time_boot_ms": int(msg.time_boot_ms),
        }
        if not self._for_us(msg):
            self.log.write("setpoint", self.t, **record, valid=False, applied=False, reason="not for us")
            return
        if self.flavour is Flavour.ARDUPILOT and self.mode != "GUIDED":
            self.log.write("setpoint", self.t, **record, valid=False, applied=False, reason="not in GUIDED")
            return
        here = (float(s.pos[0]), float(s.pos[1]), float(s.pos[2]))
        d = decode_setpoint(self.flavour, msg, here, s.yaw)
        applied = False
        reason = d.reason
        if d.valid:
            if self.t - self.last_sp > STREAM_GAP_S:
                self.stream_start = self.t
            self.last_sp = self.t
            if self.failsafe_mode is not None and self.armed and self.user_mode == "OFFBOARD":
                # PX4 re-runs the user's mode as soon as it can: one setpoint within COM_OF_LOSS_T.
                self._clear_failsafe("offboard signal regained")
        elif self.flavour is Flavour.PX4 and self.t - self._last_reject_text.get(d.reason, -math.inf) >= 1.0:
            # PX4 reports each rejection, throttled like its mavlink_log.
            self._last_reject_text[d.reason] = self.t
            self._report(mav.MAV_SEVERITY_CRITICAL, f"SET_POSITION_TARGET_LOCAL_NED {d.reason}", None)
        if d.stop:
            # ArduPilot with shaping: "stop" is GUIDED's init, zero velocity from where it is
            # (sitl_mock.ardupilot.stop_target); else a hold at the current position.
            self.follow_target = (self.ap.stop_target(self) if self.flavour is Flavour.ARDUPILOT and self.config.shaping
                                  else Target.hold(s.pos.copy(), s.yaw))
            applied = True
        elif d.setpoint is not None and self.mode == self.modes.follow_mode:
            if self.flavour is Flavour.ARDUPILOT and self.landed and not self.guided_taken_off:
                reason = "landed: takeoff first"
            else:
                sp = d.setpoint
                prev_yaw = self.follow_target.yaw if self.follow_target is not None else s.yaw
                self.follow_target = Target(
                    np.array(sp.pos), np.array(sp.vel), np.array(sp.acc),
                    sp.yaw if math.isfinite(sp.yaw) else (prev_yaw if math.isnan(sp.yaw_rate) else math.nan),
                    sp.yaw_rate,
                )
                applied = True
        elif d.setpoint is not None:
            reason = f"not in {self.modes.follow_mode}"
        tgt = self.follow_target if applied and self.follow_target is not None else None
        self.log.write(
            "setpoint", self.t, **record, valid=d.valid, applied=applied, reason=reason,
            pos=tgt.pos.tolist() if tgt else None, vel=tgt.vel.tolist() if tgt else None,
            acc=tgt.acc.tolist() if tgt else None,
        )

    def _on_param_list(self, msg: Any) -> None:
        if msg.target_system not in (0, self.config.sysid):
            return
        count = len(self.params)
        for i, p in enumerate(self.params.values()):
            self._send(tm.param_value(self.enc.mav, self.flavour, p, count, i))

    def _param_name(self, raw: Any) -> str:
        return (raw.decode(errors="replace") if isinstance(raw, bytes) else str(raw)).rstrip("\x00")

    def _on_param_read(self, msg: Any) -> None:
        if msg.target_system not in (0, self.config.sysid):
            return
        names = list(self.params)
        name = self._param_name(msg.param_id)
        if msg.param_index >= 0:
            name = names[msg.param_index] if msg.param_index < len(names) else ""
        if name in self.params:
            self._send(tm.param_value(self.enc.mav, self.flavour, self.params[name], len(names),
                                      names.index(name)))

    def _on_param_set(self, msg: Any) -> None:
        if msg.target_system not in (0, self.config.sysid):
            return
        name = self._param_name(msg.param_id)
        if name not in self.params:
            self._report(mav.MAV_SEVERITY_WARNING, f"unknown param {name}", None)
            return
        old = self.params[name]
        value = tm.decode_param_value(self.flavour, old.ptype, float(msg.param_value))
        self.params[name] = Param(name, value, old.ptype)
        self.log.write("event", self.t, event="param_set", name=name, value=value)
        names = list(self.params)
        self._send(tm.param_value(self.enc.mav, self.flavour, self.params[name], len(names),
                                  names.index(name)))

    def _on_mission_list(self, msg: Any) -> None:
        if msg.target_system not in (0, self.config.sysid):
            return
        self._send(self.enc.mav.mission_count_encode(msg.get_srcSystem(), msg.get_srcComponent(), 0,
                                                     msg.mission_type))

    def _on_timesync(self, msg: Any) -> None:
        if msg.tc1 == 0:
            now_ns = int((self.t - self.boot_t) * 1e9)
            self._send(self.enc.mav.timesync_encode(now_ns, msg.ts1))

    # ------------------------------------------------------------------ outgoing telemetry

    def _send_heartbeat(self) -> None:
        base = 0
        if self.flavour is Flavour.PX4:
            main = (self.modes.custom_mode(self.mode) >> 16) & 0xFF
            base = 29 if main in (4, 6) else 81
        else:
            base = 16 | (8 if self.modes.behaviour(self.mode) is not Behaviour.HOLD else 64)
        self._send(tm.heartbeat(self.enc.mav, self.modes.autopilot, base, self.armed,
                                self.modes.custom_mode(self.mode)))

    def _telemetry(self, target: Target | None) -> None:
        for mid, due in self.next_due.items():
            if self.t + 1e-9 >= due:
                interval = self.intervals[mid]
                if math.isinf(interval):
                    continue
                self.next_due[mid] = max(due + interval, self.t)
                self._send_stream(mid, target)

    def _noisy(self) -> tuple[np.ndarray, np.ndarray]:
        s = self.vehicle.state
        if self.config.noise <= 0:
            return s.pos, s.vel
        n = self.config.noise
        return s.pos + self.rng.normal(0, n, 3), s.vel + self.rng.normal(0, n / 2, 3)

    def _landed_state(self) -> int:
        if self.landed:
            return int(mav.MAV_LANDED_STATE_ON_GROUND)
        if self.modes.behaviour(self.mode) is Behaviour.LAND:
            return int(mav.MAV_LANDED_STATE_LANDING)
        if self.modes.behaviour(self.mode) is Behaviour.TAKEOFF:
            return int(mav.MAV_LANDED_STATE_TAKEOFF)
        return int(mav.MAV_LANDED_STATE_IN_AIR)

    def _send_stream(self, mid: int, target: Target | None) -> None:
        m = self.enc.mav
        ms = self.time_boot_ms
        t_usec = int((self.t - self.boot_t) * 1e6)
        s = self.vehicle.state
        if self.flavour is Flavour.ARDUPILOT and not self.ap.sends(mid):
            return  # no EKF origin yet (sitl_mock.ardupilot)
        if self.px4 is not None and not self.px4.sends(mid):
            return  # no global origin yet (sitl_mock.px4)
        if mid == mav.MAVLINK_MSG_ID_HEARTBEAT:
            self._send_heartbeat()
        elif mid == mav.MAVLINK_MSG_ID_SYS_STATUS:
            self._send(tm.sys_status(m, armable=not self.reject_arming))
        elif mid == mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED:
            pos, vel = self._noisy()
            if self.px4 is not None:
                pos = self.px4.estimate(pos)
            self._send(m.local_position_ned_encode(ms, *pos.tolist(), *vel.tolist()))
        elif mid == mav.MAVLINK_MSG_ID_ATTITUDE:
            roll, pitch, yaw = self.vehicle.attitude()
            self._send(m.attitude_encode(ms, roll, pitch, yaw, 0.0, 0.0, s.yaw_rate))
        elif mid == mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT:
            pos, vel = self._noisy()
            self._send(tm.global_position(m, self.origin, float(self.home_ned[2]), ms, pos, vel, s.yaw))
        elif mid == mav.MAVLINK_MSG_ID_GPS_RAW_INT:
            pos, vel = self._noisy()
            self._send(tm.gps_raw(m, self.origin, t_usec, pos, vel))
        elif mid == mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE:
            self._send(m.extended_sys_state_encode(mav.MAV_VTOL_STATE_UNDEFINED, self._landed_state()))
        elif mid == mav.MAVLINK_MSG_ID_HOME_POSITION:
            self._send(tm.home_position(m, self.origin, self.home_ned, t_usec))
        elif mid == mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN:
            self._send(tm.gps_global_origin(m, self.origin, t_usec))
        elif mid == mav.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED:
            if target is not None:
                self._send(tm.position_target(m, ms, target.pos, target.vel, target.acc, target.yaw,
                                              target.yaw_rate))
        elif mid == mav.MAVLINK_MSG_ID_SYSTEM_TIME:
            self._send(tm.system_time(m, ms))

    # ------------------------------------------------------------------ control socket

    def _control_request(self, req: dict[str, Any]) -> dict[str, Any]:
        cmd = req["cmd"]
        if cmd == "state":
            self._update_snapshot()
            return {"ok": True, **self.snapshot()}
        if cmd == "set_mode":
            if not isinstance(req.get("mode"), str):
                raise ValueError("set_mode: field 'mode' must be a string")
            ok, why = self.pilot_set_mode(req["mode"])
            return {"ok": ok, "mode": self.mode, **({"error": why} if why else {})}
        if cmd == "pause_link":
            self.pause_link(_number(req, "seconds", 0.0))
        elif cmd == "drop":
            frac = _number(req, "fraction", 0.0)
            if frac > 1.0:
                raise ValueError(f"drop: field 'fraction' must be in [0, 1], got {frac}")
            self.link_faults.drop = frac
        elif cmd == "latency":
            self.link_faults.latency_s = _number(req, "ms", 0.0) / 1000.0
        elif cmd == "reboot":
            self.reboot()
        elif cmd == "reject_arming":
            self.reject_arming = bool(req.get("value", True))
        elif cmd == "rc":
            pwm = req.get("throttle")
            if pwm is not None and (isinstance(pwm, bool) or not isinstance(pwm, int) or not 800 <= pwm <= 2200):
                raise ValueError(f"rc: field 'throttle' must be a pwm in 800..2200 or null (RC lost), got {pwm!r}")
            self.ap.set_rc(self, pwm)
        elif cmd == "set_param":
            name = str(req.get("name"))
            if name not in self.params:
                raise ValueError(f"set_param: unknown parameter {name!r}")
            self.params[name] = Param(name, _number(req, "value", -math.inf), self.params[name].ptype)
        elif cmd == "stop":
            self._stop.set()
        else:
            raise ValueError(
                f"cmd: unknown command {cmd!r}; valid: state, set_mode, pause_link, drop, latency, "
                "reboot, reject_arming, rc, set_param, stop"
            )
        self.log.write("event", self.t, event="control", request=req)
        self._update_snapshot()
        return {"ok": True}


def _int(value: float) -> int:
    """MAVLink float parameter as an integer; NaN (unset) becomes -1."""
    return round(value) if math.isfinite(value) else -1


def _number(req: dict[str, Any], name: str, minimum: float) -> float:
    value = req.get(name)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{req['cmd']}: field {name!r} must be a number")
    if value < minimum:
        raise ValueError(f"{req['cmd']}: field {name!r} must be >= {minimum}, got {value}")
    return float(value)
