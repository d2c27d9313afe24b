"""MAVLink 2 link to the autopilot (pymavlink), driven by the asyncio loop: what is said over it.

The socket side (the connection, reading it on the loop, the peer gate, TCP dialling, who
writes) is companion.wire.socket_link; it delivers every admitted message here. This module
reads them (the vehicle's own messages by companion.wire.vehicle.VehicleState, PX4's events,
parameters, command acks) and says what the companion asks: setpoints, commands and their
acks, parameter reads, telemetry requests, modes. Periodic setpoints are sent from the setpoint
thread (companion.setpoints.SetpointSender), everything else from the loop.
"""

from __future__ import annotations

import asyncio
import math
import os
import time
from collections.abc import Callable
from typing import Any

import numpy as np

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil

from companion.config import Config
from companion.sendproc import Encoding
from companion.setpoints import Setpoint
from companion.tap import Tap
from companion.wire import dialect
from companion.wire.peer import PeerGate
from companion.wire.px4_events import Px4Events
from companion.wire.socket_link import SocketLink
from companion.wire.vehicle import (
    APM_GUIDED,
    APM_LAND,
    APM_MODES,
    APM_STREAMS,
    NOTE_AFTER,
    NOTE_BEFORE,
    POSITION_ONLY_MASK,
    PX4_MODES,
    PX4_OFFBOARD,
    TYPE_MASK,
    WANTED,
    CommandFailed,
    Note,
    VehicleState,
    heard,
    param_name,
    param_value,
    result_name,
    telemetry_hint,
)

dialect.install()  # PX4 >= 1.14 says what happens in EVENT (410), which pymavlink lacks
mavlink = mavutil.mavlink


class MavlinkLink:
    def __init__(self, cfg: Config, on_message: Callable[[str, Any], None] | None = None) -> None:
        self.cfg = cfg
        self.state = VehicleState()
        self.on_message = on_message
        self.events = Px4Events(self, cfg.mavlink.events_cache_dir)  # PX4's events metadata
        self._acks: dict[int, asyncio.Future[int]] = {}
        # COMMAND_ACK names only the command, so two of one command in flight at once cannot be
        # told apart: the second waits for the first's answer (MAVSDK queues them likewise)
        self._command_locks: dict[int, asyncio.Lock] = {}
        self.boot = time.monotonic()  # monotonic s at time_boot_ms 0 in what we send
        # PARAM_VALUEs heard (name -> value in the parameter's own unit) and who waits for them
        self.params: dict[str, float] = {}
        self._param_heard = asyncio.Event()
        # the connection, its sockets, the peer gate and who writes; it hands us what it admits
        self.io = SocketLink(cfg, self.boot, self._handle)

    # -- the socket side (companion.wire.socket_link) --------------------------

    def open(self, loop: asyncio.AbstractEventLoop) -> None:
        self.io.open(loop)

    def close(self) -> None:
        self.io.close()

    @property
    def conn(self) -> Any:
        """pymavlink's connection (None before `open` and after `close`)."""
        return self.io.conn

    @property
    def gate(self) -> PeerGate | None:
        return self.io.gate

    @property
    def tap(self) -> Tap:
        return self.io.tap

    @tap.setter
    def tap(self, tap: Tap) -> None:
        self.io.tap = tap

    @property
    def on_ignored(self) -> Callable[[dict[str, int], str | None], None] | None:
        return self.io.on_ignored

    @on_ignored.setter
    def on_ignored(self, cb: Callable[[dict[str, int], str | None], None] | None) -> None:
        self.io.on_ignored = cb

    @property
    def sent_setpoints(self) -> int:
        return self.io.sent_setpoints

    def transport(self) -> tuple[int | None, bool, Encoding]:
        return self.io.transport()

    def use_writer(self, writer: Any) -> None:
        self.io.use_writer(writer)

    def send_heartbeat(self) -> None:
        self.io.send_heartbeat()

    # -- receive -------------------------------------------------------------

    def _handle(self, msg: Any) -> None:
        kind = msg.get_type()
        now = time.monotonic()
        self.tap.mavlink_received(msg, now)
        st = self.state
        if not st.take(kind, msg, now, self.cfg.vehicle.autopilot_component):
            return  # a heartbeat not from the autopilot
        if kind == "AUTOPILOT_VERSION":
            self.events.on_message(kind, msg)  # the events metadata is keyed by the firmware
        elif kind == "EVENT":
            info = dialect.decode_event(msg)
            said = self.events.describe(info.id, dialect.event_arguments(msg))
            if said is not None:
                st.notes.append(Note(now, "event", said.text, info.level, info.id, said.name, words=True))
            else:
                st.notes.append(Note(now, "event", self.events.unknown(info.id), info.level, info.id, info.name))
        elif kind in ("FILE_TRANSFER_PROTOCOL", "COMPONENT_METADATA"):
            self.events.on_message(kind, msg)
        elif kind == "PARAM_VALUE" and msg.get_srcComponent() == self.cfg.vehicle.autopilot_component:
            name = param_name(msg.param_id)
            value = param_value(st.autopilot, int(msg.param_type), float(msg.param_value))
            if name and math.isfinite(value):
                self.params[name] = value
                self._param_heard.set()
        elif kind == "COMMAND_ACK":
            fut = self._acks.pop(msg.command, None)
            if fut is not None and not fut.done():
                fut.set_result(int(msg.result))
        if self.on_message is not None:
            self.on_message(kind, msg)

    def link_ok(self, now: float | None = None) -> bool:
        """The autopilot is heard: a heartbeat once, then any of its messages within
        link_timeout (the telemetry at tens of Hz, not only the 1 Hz heartbeat, so that a lossy
        radio link is not declared lost for two heartbeats missed in a row)."""
        now = time.monotonic() if now is None else now
        return heard(self.state.last_heartbeat, self.state.last_message, self.cfg.mavlink.link_timeout, now)


    # -- send ----------------------------------------------------------------

    def send_message(self, msg: Any) -> None:
        """Any encoded message (thread-safe)."""
        self.io.send(msg)

    def setpoint_message(self, sp: Setpoint, at: float | None = None) -> Any:
        """SET_POSITION_TARGET_LOCAL_NED for `sp`, stamped at monotonic `at` (now)."""
        p, v, a = sp.position, sp.velocity, sp.acceleration
        at = time.monotonic() if at is None else at
        return self.conn.mav.set_position_target_local_ned_encode(
            int((at - self.boot) * 1000) & 0xFFFFFFFF,
            self.cfg.vehicle.sysid,
            self.cfg.vehicle.autopilot_component,
            mavlink.MAV_FRAME_LOCAL_NED,
            TYPE_MASK,
            float(p[0]), float(p[1]), float(p[2]),
            float(v[0]), float(v[1]), float(v[2]),
            float(a[0]), float(a[1]), float(a[2]),
            float(sp.yaw),
            0.0,
        )

    def send_setpoint(self, sp: Setpoint) -> None:
        """Thread-safe (called from the setpoint thread and, for a swap, from the loop)."""
        self.io.send(self.setpoint_message(sp), setpoint=True)

    def send_position_target(self, position: np.ndarray, yaw: float) -> None:
        """One position-only target (ArduPilot GUIDED keeps holding it with no timeout)."""
        p = position
        msg = self.conn.mav.set_position_target_local_ned_encode(
            int((time.monotonic() - self.boot) * 1000) & 0xFFFFFFFF,
            self.cfg.vehicle.sysid, self.cfg.vehicle.autopilot_component, mavlink.MAV_FRAME_LOCAL_NED,
            POSITION_ONLY_MASK, float(p[0]), float(p[1]), float(p[2]), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, float(yaw), 0.0)
        self.io.send(msg)

    async def command(self, command: int, *params: float, timeout: float | None = None) -> int:
        """COMMAND_LONG and wait for its COMMAND_ACK; returns MAV_RESULT. A second caller of the
        same command (the link-up's HOME_POSITION request beside an operator's, say) waits for
        the first's ACK or timeout, then sends its own."""
        lock = self._command_locks.setdefault(command, asyncio.Lock())
        async with lock:
            return await self._command_once(command, params, timeout)

    async def _command_once(self, command: int, params: tuple[float, ...], timeout: float | None) -> int:
        loop = self.io.loop
        assert loop is not None
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        fut: asyncio.Future[int] = loop.create_future()
        self._acks[command] = fut
        self.io.send(self.conn.mav.command_long_encode(self.cfg.vehicle.sysid, self.cfg.vehicle.autopilot_component,
                                                       command, 0, *p))
        try:
            return await asyncio.wait_for(fut, timeout or self.cfg.mavlink.command_timeout)
        except TimeoutError:
            raise CommandFailed(f"no COMMAND_ACK for command {command}") from None
        finally:
            if self._acks.get(command) is fut:
                del self._acks[command]

    async def command_ok(self, what: str, command: int, *params: float) -> None:
        sent = time.monotonic()
        result = await self.command(command, *params)
        if result != mavlink.MAV_RESULT_ACCEPTED:
            name = result_name(result)
            acked = time.monotonic()
            note = await self.note_around(acked, since=sent - NOTE_BEFORE)
            reasons = self.reasons_around(sent - NOTE_BEFORE, acked + NOTE_AFTER)
            if reasons:
                text = f" ({'; '.join(reasons)})"
            else:
                text = "" if note is None else f" ({note.source} {note.text!r}, {note.level})"
            raise CommandFailed(f"{what} refused by the autopilot: {name}{text}", name, note, reasons)

    async def note_around(self, acked: float, since: float) -> Note | None:
        """The last EVENT/STATUSTEXT from `since` to the ACK, else the first within NOTE_AFTER
        after it (PX4 may send its event just after the ACK)."""
        before = [n for n in self.state.notes if since <= n.at <= acked]
        if before:
            return before[-1]
        deadline = acked + NOTE_AFTER
        while time.monotonic() < deadline:
            await asyncio.sleep(0.02)
            after = [n for n in self.state.notes if n.at > acked]
            if after:
                return after[0]
        return None

    def reasons_around(self, since: float, until: float) -> tuple[str, ...]:
        """What the autopilot said in words from `since` to `until`, as reasons for a refusal:
        PX4's events of level WARNING or worse (not its protocol summaries), ArduPilot's
        `PreArm:` / `Arm:` texts and other STATUSTEXT of level WARNING or worse; each once."""
        out: list[str] = []
        for n in self.state.notes:
            if not since <= n.at <= until:
                continue
            serious = n.level in ("EMERGENCY", "ALERT", "CRITICAL", "ERROR", "WARNING")
            prearm = n.source == "statustext" and n.text.startswith(("PreArm:", "Arm:"))
            if (serious or prearm) and n.text not in out:
                out.append(n.text)
        return tuple(out)

    async def read_params(self, names: list[str], timeout: float, retries: int) -> dict[str, float]:
        """PARAM_REQUEST_READ by name for each of `names`, asked again (up to `retries` more
        times, `timeout` s apart) for those not answered; returns those answered (values in
        the parameter's own unit). Neither autopilot answers for a name it does not have."""
        wanted = list(dict.fromkeys(names))
        for n in wanted:  # answers from now on only (after a reconnect, values may have changed)
            self.params.pop(n, None)
        for _ in range(retries + 1):
            missing = [n for n in wanted if n not in self.params]
            if not missing:
                break
            self.io.send(*(self.conn.mav.param_request_read_encode(self.cfg.vehicle.sysid,
                                                                   self.cfg.vehicle.autopilot_component,
                                                                   n.encode()[:16], -1) for n in missing))
            deadline = time.monotonic() + timeout
            while any(n not in self.params for n in missing) and (left := deadline - time.monotonic()) > 0:
                self._param_heard.clear()
                try:
                    await asyncio.wait_for(self._param_heard.wait(), left)
                except TimeoutError:
                    break
        return {n: self.params[n] for n in wanted if n in self.params}

    async def request_home(self) -> None:
        """Ask for HOME_POSITION once (MAV_CMD_REQUEST_MESSAGE); the answer is the message."""
        result = await self.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_HOME_POSITION)
        if result != mavlink.MAV_RESULT_ACCEPTED:
            raise CommandFailed(f"HOME_POSITION request refused: {result_name(result)}", result_name(result))

    async def request_origin(self) -> None:
        """Ask for GPS_GLOBAL_ORIGIN once (MAV_CMD_REQUEST_MESSAGE): the local frame's geodetic
        origin, which places the vehicle in the fleet frame ([fleet] origin)."""
        result = await self.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN)
        if result != mavlink.MAV_RESULT_ACCEPTED:
            raise CommandFailed(f"GPS_GLOBAL_ORIGIN request refused: {result_name(result)}", result_name(result))

    async def set_follow_mode(self) -> None:
        """OFFBOARD (PX4) or GUIDED (ArduPilot) via MAV_CMD_DO_SET_MODE."""
        if self.state.autopilot == "px4":
            await self.command_ok("OFFBOARD", mavlink.MAV_CMD_DO_SET_MODE, 1, PX4_OFFBOARD, 0)
        else:
            await self.command_ok("GUIDED", mavlink.MAV_CMD_DO_SET_MODE, 1, APM_GUIDED)

    async def arm(self, value: bool) -> None:
        await self.command_ok("arm" if value else "disarm", mavlink.MAV_CMD_COMPONENT_ARM_DISARM, 1.0 if value else 0.0)

    async def takeoff(self, altitude: float) -> None:
        await self.command_ok("takeoff", mavlink.MAV_CMD_NAV_TAKEOFF, 0, 0, 0, math.nan, math.nan, math.nan, altitude)

    async def request_telemetry(self) -> dict[str, str]:
        """Ask for each message in WANTED at its rate: MAV_CMD_SET_MESSAGE_INTERVAL, and for
        ArduPilot also the legacy REQUEST_DATA_STREAM of its group. Returns, per message, what
        the autopilot answered when it did not accept the interval."""
        answers: dict[str, str] = {}
        if self.state.autopilot == "ardupilot":
            groups: dict[int, float] = {}
            for name, hz in WANTED.items():
                group = APM_STREAMS[name][0]
                groups[group] = max(groups.get(group, 0.0), hz)
            self.io.send(*(self.conn.mav.request_data_stream_encode(self.cfg.vehicle.sysid,
                                                                    self.cfg.vehicle.autopilot_component,
                                                                    group, max(1, round(hz)), 1)
                           for group, hz in groups.items()))
        for name, hz in WANTED.items():
            msg_id = getattr(mavlink, f"MAVLINK_MSG_ID_{name}")
            try:
                result = await self.command(mavlink.MAV_CMD_SET_MESSAGE_INTERVAL, msg_id, 1e6 / hz)
            except CommandFailed as exc:
                answers[name] = str(exc)
                continue
            if result != mavlink.MAV_RESULT_ACCEPTED:
                answers[name] = result_name(result)
        return answers

    def missing_telemetry(self, since: float) -> list[str]:
        """The messages in WANTED that have not arrived since `since` (monotonic)."""
        return [name for name in WANTED if self.state.received.get(name, -math.inf) < since]

    async def request_version(self) -> None:
        """AUTOPILOT_VERSION (which rate parameters ArduPilot has); a refusal is not fatal."""
        await self.command(mavlink.MAV_CMD_REQUEST_MESSAGE, mavlink.MAVLINK_MSG_ID_AUTOPILOT_VERSION)

    def telemetry_hint(self, missing: list[str]) -> str:
        """How to make the autopilot send `missing` (companion.wire.vehicle.telemetry_hint)."""
        return telemetry_hint(self.state.autopilot, missing, self.cfg.mavlink.url, self.state.sw_version)

    async def set_mode(self, name: str) -> None:
        """One of PX4_MODES / APM_MODES by MAV_CMD_DO_SET_MODE (custom mode enabled)."""
        if self.state.autopilot == "px4":
            main, sub = PX4_MODES[name]
            await self.command_ok(name, mavlink.MAV_CMD_DO_SET_MODE, 1, main, sub)
        else:
            await self.command_ok(name, mavlink.MAV_CMD_DO_SET_MODE, 1, APM_MODES[name])

    async def restore_mode(self, base_mode: int, custom_mode: int) -> None:
        """Back to a mode as a heartbeat reported it (base_mode, custom_mode)."""
        if self.state.autopilot == "px4":
            main, sub = (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
            await self.command_ok("the previous mode", mavlink.MAV_CMD_DO_SET_MODE, 1, main, sub)
        else:
            await self.command_ok("the previous mode", mavlink.MAV_CMD_DO_SET_MODE, 1, custom_mode)

    async def land(self) -> None:
        if self.state.autopilot == "px4":
            await self.command_ok("land", mavlink.MAV_CMD_NAV_LAND, 0, 0, 0, math.nan, math.nan, math.nan, math.nan)
        else:
            await self.command_ok("LAND", mavlink.MAV_CMD_DO_SET_MODE, 1, APM_LAND)

    async def wait_for(self, predicate: Callable[[VehicleState], bool], timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while not predicate(self.state):
            if time.monotonic() > deadline:
                raise CommandFailed(f"timed out after {timeout:.1f} s waiting for {what}")
            await asyncio.sleep(0.02)
