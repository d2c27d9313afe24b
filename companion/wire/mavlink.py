"""MAVLink 2 link to the autopilot (pymavlink), driven by the asyncio loop.

The connection's file descriptor is registered with `loop.add_reader`, so
decoding happens on the loop thread; sending is a non-blocking sendto. Periodic
setpoints are sent from the setpoint thread (companion.setpoints.SetpointSender),
everything else from the loop: sends are serialised by a lock, as pymavlink's
packet sequence counter is not thread-safe. A TCP link is dialled, and re-dialled
after a loss, by a thread of its own (companion.wire.tcp): nothing here ever waits
for a connect.
"""

from __future__ import annotations

import asyncio
import contextlib
import logging
import math
import os
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

import numpy as np

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil

from companion.config import Config
from companion.sendproc import Encoding
from companion.setpoints import Setpoint
from companion.tap import NO_TAP, Tap
from companion.wire import dialect
from companion.wire.peer import OTHER_ID, UNBOUND, PeerGate, SignatureCheck
from companion.wire.px4_events import Px4Events
from companion.wire.signing import read_signing_key
from companion.wire.tcp import Dialler, TcpConnection, describe, tcp_address
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
    param_name,
    param_value,
    parse_url,
    result_name,
    telemetry_hint,
)

log = logging.getLogger("companion")
dialect.install()  # PX4 >= 1.14 says what happens in EVENT (410), which pymavlink lacks
mavlink = mavutil.mavlink

IGNORED_EVERY = 5.0  # s between two reports of messages ignored as not the autopilot's
IGNORED_OTHER_ID_EVERY = 60.0  # the same for other ids (a GCS or camera on a shared link)


class MavlinkLink:
    def __init__(self, cfg: Config, on_message: Callable[[str, Any], None] | None = None) -> None:
        self.cfg = cfg
        self.state = VehicleState()
        self.on_message = on_message
        self.events = Px4Events(self, cfg.mavlink.events_cache_dir)  # PX4's events metadata
        self.conn: Any = None
        self._loop: asyncio.AbstractEventLoop | None = None
        self._acks: dict[int, asyncio.Future[int]] = {}
        self._boot = time.monotonic()
        self._send_lock = threading.Lock()
        self._sent = 0
        self._writer: Any = None  # companion.sendproc.SetpointProcess once it writes for us
        self.tap: Tap = NO_TAP  # the flight recorder (companion/tap.py)
        # PARAM_VALUEs heard (name -> value in the parameter's own unit) and who waits for them
        self.params: dict[str, float] = {}
        self._param_heard = asyncio.Event()
        self.gate: PeerGate | None = None
        self.signature: SignatureCheck | None = None
        # `on_ignored(counts, rebound)`: messages not from the bound autopilot were ignored since
        # the last call (counts by reason), or the link re-bound to a new address; called on the
        # loop at most every IGNORED_EVERY seconds per reason (OTHER_ID: IGNORED_OTHER_ID_EVERY)
        self.on_ignored: Callable[[dict[str, int], str | None], None] | None = None
        self._ignored_said: dict[str, tuple[float, int]] = {}
        self._sock: Any = None  # UDP: the socket read here, datagram by datagram
        self._udp_server = False
        self._dialler: Dialler | None = None  # TCP: dials the autopilot off the loop
        self._reading: int | None = None  # the descriptor registered with the loop
        self._tcp_where = "?"  # the TCP connection's ends, for the log (unknown once the peer is gone)

    # -- lifecycle -----------------------------------------------------------

    def open(self, loop: asyncio.AbstractEventLoop) -> None:
        v = self.cfg.vehicle
        device, baud = parse_url(self.cfg.mavlink.url)
        if device.startswith("tcp:"):
            # not pymavlink's mavtcp: it dials in the constructor and re-dials inside recv and
            # write, on the loop (companion.wire.tcp)
            self.conn = TcpConnection(tcp_address(device), v.sysid, v.component)
        else:
            self.conn = mavutil.mavlink_connection(device, baud=baud, source_system=v.sysid,
                                                   source_component=v.component, autoreconnect=True)
        self.conn.mav.robust_parsing = True
        self.conn.mav.set_send_callback(self.tap.mavlink_sent)  # after each write: O(1), never waits
        mc = self.cfg.mavlink
        keyed = bool(mc.signing_key_file)
        if keyed:
            # Sign everything we send. pymavlink passes every message up (allow_unsigned); whether
            # it was signed with our key (get_signed) is judged by the gate.
            self.conn.setup_signing(read_signing_key(mc.signing_key_file), sign_outgoing=True,
                                    allow_unsigned_callback=lambda _mav, _msg_id: True)
            self.signature = SignatureCheck(self.conn.mav)
            self.conn.mav.check_signature = self.signature
        require = keyed and mc.require_signed_inbound
        self._sock = getattr(self.conn, "port", None) if isinstance(self.conn, mavutil.mavudp) else None
        self._udp_server = bool(self._sock is not None and self.conn.udp_server)
        self.gate = PeerGate(v.sysid, v.autopilot_component, udp=self._sock is not None, require_signed=require,
                             link_timeout=mc.link_timeout)
        if self._sock is not None and not self._udp_server:
            # udpout: we talk to the configured address; only it is heard
            host, port = self.conn.destination_addr
            self.gate.address, self.gate.pinned = (socket.gethostbyname(host), int(port)), True
        if self._udp_server:
            # pymavlink's udpin answers every address that ever sent a datagram: a spoofer would
            # receive our setpoints. Only the bound autopilot's address is written to.
            self.conn.write = self._write_bound
        self._loop = loop
        if isinstance(self.conn, TcpConnection):
            self.conn.on_lost = self._tcp_lost_elsewhere
            self._dialler = Dialler(self.conn.destination_addr, self._tcp_dialled)
            self._dialler.start()
            self._dialler.dial()  # the first connection too: the service starts without it, as with UDP
            return
        self._read(self.conn.fd)
        self.send_heartbeat()

    def _read(self, fd: int | None) -> None:
        """Read `fd` on the loop from now on (None: nothing), and no longer the one read so far.
        The old one is unregistered before anyone closes it: epoll would otherwise go on
        reporting a socket that the setpoint process still holds a copy of."""
        assert self._loop is not None
        if self._reading is not None:
            self._loop.remove_reader(self._reading)
        self._reading = fd
        if fd is not None:
            self._loop.add_reader(fd, self._readable)

    # -- TCP: the connection lost and made again, off the loop -------------------------------

    def _tcp_lost_elsewhere(self, sock: socket.socket, why: str) -> None:
        """TcpConnection saw its connection end, on the loop or on the setpoint thread."""
        loop = self._loop
        if loop is None:
            sock.close()
            return
        try:
            loop.call_soon_threadsafe(self._tcp_lost, sock, why)
        except RuntimeError:  # the loop is closed: nobody reads any more
            sock.close()

    def _tcp_lost(self, sock: socket.socket, why: str) -> None:
        if self._reading == sock.fileno():
            self._read(None)
        sock.close()
        if self._writer is not None:
            self._writer.use_fd(None)  # its copy closed too: the old connection is gone on our side
        if self.conn is None or self._dialler is None:
            return  # closing
        log.warning("MAVLink TCP connection %s lost (%s): reconnecting off the event loop; the link "
                    "is judged by the autopilot's heartbeats as ever", self._tcp_where, why)
        self._dialler.dial()

    def _tcp_dialled(self, sock: socket.socket) -> None:
        """The dialler connected (on its thread): the loop takes the connection over."""
        loop = self._loop
        try:
            assert loop is not None
            loop.call_soon_threadsafe(self._tcp_connected, sock)
        except (RuntimeError, AssertionError):
            sock.close()

    def _tcp_connected(self, sock: socket.socket) -> None:
        conn = self.conn
        if conn is None or not isinstance(conn, TcpConnection):
            sock.close()  # closed meanwhile
            return
        with self._send_lock:
            conn.attach(sock)
        self._read(sock.fileno())
        if self._writer is not None:
            # the setpoint process writes to a copy of the connection's descriptor: hand it the
            # new one, before anything else it is asked to send
            self._writer.use_fd(sock.fileno())
        attempts = self._dialler.attempts if self._dialler is not None else 0
        self._tcp_where = describe(sock)
        log.info("MAVLink TCP connected %s (attempt %d)", self._tcp_where, attempts)
        self.send_heartbeat()

    @property
    def sent_setpoints(self) -> int:
        """Setpoints that left: ours (a swap's immediate one; every one with a setpoint thread)
        and, once it writes for us, the setpoint process's periodic ones."""
        return self._sent + (self._writer.sent if self._writer is not None else 0)

    def transport(self) -> tuple[int | None, bool, Encoding]:
        """What a setpoint process needs to write to the autopilot itself: the link's
        descriptor, whether it is a datagram socket, and how to pack (companion.sendproc)."""
        conn, v = self.conn, self.cfg.vehicle
        datagram = isinstance(conn, mavutil.mavudp)
        fd = conn.port.fileno() if datagram else conn.fd  # None: a TCP link not connected (yet)
        key = read_signing_key(self.cfg.mavlink.signing_key_file) if self.cfg.mavlink.signing_key_file else None
        return fd, datagram, Encoding(v.sysid, v.component, v.sysid, v.autopilot_component, key, self._boot)

    def use_writer(self, writer: Any) -> None:
        """From now on `writer` (a running SetpointProcess) packs and writes every message we
        send, so that one process owns the packet sequence and the signing timestamps; while it
        does not run (before start, after stop) we write ourselves."""
        direct = self.conn.mav.send

        def send(msg: Any, force_mavlink1: bool = False) -> None:
            if writer.post_message(msg):
                self.tap.mavlink_sent(msg)  # as pymavlink's send callback would, once written
            else:
                direct(msg, force_mavlink1=force_mavlink1)

        self.conn.mav.send = send
        self._writer = writer
        self._update_route()

    def _update_route(self) -> None:
        if self._writer is None or not isinstance(self.conn, mavutil.mavudp):
            return
        # the bound autopilot's address only: a spoofer never receives a setpoint (PeerGate)
        gate = self.gate
        self._writer.route((gate.address,) if gate is not None and gate.address is not None else ())

    def close(self) -> None:
        if self.conn is None:
            return
        if self._dialler is not None:
            self._dialler.stop()
            self._dialler = None
        if self._loop is not None:
            self._read(None)
        self.conn.close()
        self.conn = None

    # -- receive -------------------------------------------------------------

    def _write_bound(self, buf: bytes) -> None:
        gate = self.gate
        if gate is None or gate.address is None:
            return  # nobody to talk to before the autopilot is heard
        with contextlib.suppress(OSError):
            self._sock.sendto(buf, gate.address)

    def _readable(self) -> None:
        if self._sock is not None:
            self._read_datagrams()
            self._say_ignored()
            self._update_route()
            return
        for _ in range(200):  # bounded so a flood cannot starve the loop
            try:
                msg = self.conn.recv_msg()
            except (OSError, ValueError):
                return
            if msg is None:
                break
            self._admit(msg, None)
        self._say_ignored()
        self._update_route()

    def _read_datagrams(self) -> None:
        """UDP: each datagram parsed on its own, so every message is known with its sender."""
        mav = self.conn.mav
        assert self.gate is not None
        for _ in range(200):  # bounded so a flood cannot starve the loop
            try:
                data, addr = self._sock.recvfrom(65535)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:  # ICMP port unreachable from a peer not up yet
                return
            if not self.gate.address_ok(addr, time.monotonic()):
                continue
            # nothing left over from another sender's datagram prefixes this one
            mav.buf, mav.buf_index, mav.expected_length = bytearray(), 0, mavlink.HEADER_LEN_V1 + 2
            mav.have_prefix_error = False
            try:
                msgs = mav.parse_buffer(data) or []
            except mavlink.MAVError:
                continue
            for msg in msgs:
                self._admit(msg, addr)

    def _admit(self, msg: Any, addr: tuple[str, int] | None) -> None:
        if msg.get_type() == "BAD_DATA":
            return
        assert self.gate is not None
        rebinds = len(self.gate.rebinds)
        if self.gate.admit(msg, addr, time.monotonic()) is not None:
            return
        if len(self.gate.rebinds) > rebinds and self.on_ignored is not None:
            old, new = self.gate.rebinds[-1]
            self.on_ignored({}, f"{old[0]}:{old[1]} -> {new[0]}:{new[1]}" if old else f"{new[0]}:{new[1]}")
        self._handle(msg)

    def _say_ignored(self) -> None:
        """Counts of ignored messages, rate-limited per reason (another id: a GCS or a camera
        on a shared link is common and harmless, so said rarely)."""
        gate, cb = self.gate, self.on_ignored
        if gate is None or cb is None or not gate.ignored:
            return
        now = time.monotonic()
        fresh: dict[str, int] = {}
        for why, total in gate.ignored.items():
            if why == UNBOUND:  # telemetry that came before the first heartbeat: normal at link-up
                continue
            said_at, said_total = self._ignored_said.get(why, (-math.inf, 0))
            every = IGNORED_OTHER_ID_EVERY if why == OTHER_ID else IGNORED_EVERY
            if total > said_total and now - said_at >= every:
                fresh[why] = total - said_total
                self._ignored_said[why] = (now, total)
        if fresh:
            cb(fresh, None)

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
        st = self.state
        if st.last_heartbeat == -math.inf:
            return False
        return now - max(st.last_heartbeat, st.last_message) <= self.cfg.mavlink.link_timeout

    # -- send ----------------------------------------------------------------

    def send_heartbeat(self) -> None:
        with self._send_lock:
            self.conn.mav.heartbeat_send(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
            )

    def send_message(self, msg: Any) -> None:
        """Any encoded message (thread-safe)."""
        with self._send_lock:
            self.conn.mav.send(msg)

    def setpoint_message(self, sp: Setpoint, at: float | None = None) -> Any:
        """SET_POSITION_TARGET_LOCAL_NED for `sp`, stamped at monotonic `at` (now)."""
        p, v, a = sp.position, sp.velocity, sp.acceleration
        at = time.monotonic() if at is None else at
        return self.conn.mav.set_position_target_local_ned_encode(
            int((at - self._boot) * 1000) & 0xFFFFFFFF,
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
        msg = self.setpoint_message(sp)
        with self._send_lock:
            self.conn.mav.send(msg)
            self._sent += 1

    def send_position_target(self, position: np.ndarray, yaw: float) -> None:
        """One position-only target (ArduPilot GUIDED keeps holding it with no timeout)."""
        p = position
        msg = self.conn.mav.set_position_target_local_ned_encode(
            int((time.monotonic() - self._boot) * 1000) & 0xFFFFFFFF,
            self.cfg.vehicle.sysid, self.cfg.vehicle.autopilot_component, mavlink.MAV_FRAME_LOCAL_NED,
            POSITION_ONLY_MASK, float(p[0]), float(p[1]), float(p[2]), 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, float(yaw), 0.0)
        with self._send_lock:
            self.conn.mav.send(msg)

    async def command(self, command: int, *params: float, timeout: float | None = None) -> int:
        """COMMAND_LONG and wait for its COMMAND_ACK; returns MAV_RESULT."""
        assert self._loop is not None
        p = [float(x) for x in params] + [0.0] * (7 - len(params))
        fut: asyncio.Future[int] = self._loop.create_future()
        old = self._acks.get(command)
        if old is not None and not old.done():
            old.cancel()
        self._acks[command] = fut
        with self._send_lock:
            self.conn.mav.command_long_send(
                self.cfg.vehicle.sysid, self.cfg.vehicle.autopilot_component, command, 0, *p
            )
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
            with self._send_lock:
                for n in missing:
                    self.conn.mav.param_request_read_send(self.cfg.vehicle.sysid, self.cfg.vehicle.autopilot_component,
                                                          n.encode()[:16], -1)
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
            with self._send_lock:
                for group, hz in groups.items():
                    self.conn.mav.request_data_stream_send(self.cfg.vehicle.sysid, self.cfg.vehicle.autopilot_component,
                                                           group, max(1, round(hz)), 1)
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
