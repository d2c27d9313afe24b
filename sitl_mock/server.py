"""MockAutopilot: one thread, one select loop, a fixed-rate simulation paced to real time.

Its parts, each a layer on the one below: `server_state.AutopilotState` (the shared state and
sending), `server_telemetry.TelemetryStreams` (outgoing telemetry), `server_modes.ModeRules` (modes
and arming per autopilot), `server_step.Simulation` (the simulation step), `server_handlers.
MavlinkHandlers` (incoming MAVLink). This module holds the endpoint: construction, the sockets,
the loop and the control socket; `MockConfig` and the constants are in `server_config`.
"""

from __future__ import annotations

import math
import select
import threading
import time
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mav

from . import px4
from . import telemetry as tm
from .ardupilot import ArduPilotRules
from .control import ControlServer, parse_hostport
from .faults import LinkFaults
from .log import FlightLog
from .protocol import Flavour, ModeTable, Param, default_params
from .server_config import APM_GROUPS as APM_GROUPS
from .server_config import ARM_REASON as ARM_REASON
from .server_config import DEFAULT_GROUND_Z as DEFAULT_GROUND_Z
from .server_config import DEFAULT_RATES as DEFAULT_RATES
from .server_config import FAILSAFE_ACTION as FAILSAFE_ACTION
from .server_config import REBOOT_SILENCE_S as REBOOT_SILENCE_S
from .server_config import STREAM_GAP_S as STREAM_GAP_S
from .server_config import MockConfig as MockConfig
from .server_handlers import MavlinkHandlers
from .transport import Encoder, Link, parse_endpoint
from .vehicle import DEFAULT_RESPONSE, RESPONSES, Vehicle

R = mav  # result and enum constants live on the dialect module


class MockAutopilot(MavlinkHandlers):
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
        self.ap = ArduPilotRules(config.rc_throttle, config.ekf_origin_delay_s, config.spool_up_s, config.shaping,
                                 config.position_after_origin_s, config.home_shift_at_arming)
        # PX4 readiness, component metadata and FTP (sitl_mock.px4); None for ArduPilot.
        ready_s = px4.DEFAULT_READY_S if config.px4_ready_s is None else config.px4_ready_s
        drift = px4.DRIFT_XY_M if config.px4_drift_m is None else config.px4_drift_m
        self.px4 = (px4.Px4Rules(self, ready_s, config.px4_report_every_s, drift)
                    if self.flavour is Flavour.PX4 else None)
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
                self._dial()
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

    def _dial(self) -> None:
        """tcpout endpoints: connect when not connected (sitl_mock.transport.TCP_REDIAL_S apart)."""
        for link in self.links:
            if link.maintain(time.monotonic()):
                self.log.write("event", self.t, event="tcp_connected", endpoint=str(link.endpoint),
                               connects=link.connects)

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
        elif cmd == "drop_tcp":
            # every TCP connection closed, as a router or a cable drops it; tcpout dials again
            return {"ok": True, "closed": sum(link.drop() for link in self.links)}
        elif cmd == "stop":
            self._stop.set()
        else:
            raise ValueError(
                f"cmd: unknown command {cmd!r}; valid: state, set_mode, pause_link, drop, latency, "
                "reboot, reject_arming, rc, set_param, drop_tcp, stop"
            )
        self.log.write("event", self.t, event="control", request=req)
        self._update_snapshot()
        return {"ok": True}


def _number(req: dict[str, Any], name: str, minimum: float) -> float:
    value = req.get(name)
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise ValueError(f"{req['cmd']}: field {name!r} must be a number")
    if value < minimum:
        raise ValueError(f"{req['cmd']}: field {name!r} must be >= {minimum}, got {value}")
    return float(value)
