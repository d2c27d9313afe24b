"""The socket side of the MAVLink link: the connection (UDP, TCP or serial), reading it on the
asyncio loop, the peer gate, and who writes.

The connection's file descriptor is registered with `loop.add_reader`, so decoding happens on
the loop thread; sending is a non-blocking sendto. Sends are serialised by a lock, as
pymavlink's packet sequence counter is not thread-safe; once a setpoint process writes for us
(companion.sendproc), it packs and writes everything. A TCP link is dialled, and re-dialled
after a loss, by a thread of its own (companion.wire.tcp): nothing here ever waits for a
connect. Every message the gate admits is delivered to the link (companion.wire.mavlink), which
reads what it says. One owner: `SocketLink` (held by MavlinkLink) owns the connection and the
sockets, the gate and the counts of what it ignored.
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

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil

from companion.config import Config
from companion.sendproc import Encoding
from companion.tap import NO_TAP, Tap
from companion.wire.peer import OTHER_ID, UNBOUND, PeerGate, SignatureCheck
from companion.wire.signing import read_signing_key
from companion.wire.tcp import Dialler, Listener, TcpConnection, describe, tcp_address
from companion.wire.vehicle import parse_url

log = logging.getLogger("companion")
mavlink = mavutil.mavlink

IGNORED_EVERY = 5.0  # s between two reports of messages ignored as not the autopilot's
IGNORED_OTHER_ID_EVERY = 60.0  # the same for other ids (a GCS or camera on a shared link)


class SocketLink:
    def __init__(self, cfg: Config, boot: float, deliver: Callable[[Any], None]) -> None:
        self.cfg = cfg
        self.boot = boot  # monotonic s at time_boot_ms 0: the link's, which the setpoint process stamps with too
        self.deliver = deliver  # a message the gate admitted, to the link that reads it
        self.conn: Any = None
        self.loop: asyncio.AbstractEventLoop | None = None
        self._send_lock = threading.Lock()
        self._sent = 0
        self._writer: Any = None  # companion.sendproc.SetpointProcess once it writes for us
        self.tap: Tap = NO_TAP  # the flight recorder (companion/tap.py)
        self.gate: PeerGate | None = None
        self.signature: SignatureCheck | None = None
        # `on_ignored(counts, rebound)`: messages not from the bound autopilot were ignored since
        # the last call (counts by reason), or the link re-bound to a new address; called on the
        # loop at most every IGNORED_EVERY seconds per reason (OTHER_ID: IGNORED_OTHER_ID_EVERY)
        self.on_ignored: Callable[[dict[str, int], str | None], None] | None = None
        self._ignored_said: dict[str, tuple[float, int]] = {}
        self._sock: Any = None  # UDP: the socket read here, datagram by datagram
        self._udp_server = False
        self._dialler: Dialler | Listener | None = None  # TCP: dials (or accepts) the autopilot off the loop
        self._reading: int | None = None  # the descriptor registered with the loop
        self._tcp_where = "?"  # the TCP connection's ends, for the log (unknown once the peer is gone)

    # -- lifecycle -----------------------------------------------------------

    def open(self, loop: asyncio.AbstractEventLoop) -> None:
        v = self.cfg.vehicle
        device, baud = parse_url(self.cfg.mavlink.url)
        if device.startswith(("tcp:", "tcpin:")):
            # not pymavlink's mavtcp: it dials in the constructor and re-dials inside recv and
            # write, on the loop; nor its mavtcpin, which swaps descriptors inside recv and never
            # sees a connection end (companion.wire.tcp)
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
        self.loop = loop
        if isinstance(self.conn, TcpConnection):
            self.conn.on_lost = self._tcp_lost_elsewhere
            # tcpin: the autopilot dials us; the Listener accepts as the Dialler would dial
            maker = Listener if device.startswith("tcpin:") else Dialler
            self._dialler = maker(self.conn.destination_addr, self._tcp_dialled)
            self._dialler.start()
            self._dialler.dial()  # the first connection too: the service starts without it, as with UDP
            return
        self._read(self.conn.fd)
        self.send_heartbeat()

    def _read(self, fd: int | None) -> None:
        """Read `fd` on the loop from now on (None: nothing), and no longer the one read so far.
        The old one is unregistered before anyone closes it: epoll would otherwise go on
        reporting a socket that the setpoint process still holds a copy of."""
        assert self.loop is not None
        if self._reading is not None:
            self.loop.remove_reader(self._reading)
        self._reading = fd
        if fd is not None:
            self.loop.add_reader(fd, self._readable)

    # -- TCP: the connection lost and made again, off the loop -------------------------------

    def _tcp_lost_elsewhere(self, sock: socket.socket, why: str) -> None:
        """TcpConnection saw its connection end, on the loop or on the setpoint thread."""
        loop = self.loop
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
        again = ("waiting for the autopilot to connect again" if isinstance(self._dialler, Listener)
                 else "reconnecting off the event loop")
        log.warning("MAVLink TCP connection %s lost (%s): %s; the link is judged by the autopilot's "
                    "heartbeats as ever", self._tcp_where, why, again)
        self._dialler.dial()

    def _tcp_dialled(self, sock: socket.socket) -> None:
        """The dialler connected (on its thread): the loop takes the connection over."""
        loop = self.loop
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
        return fd, datagram, Encoding(v.sysid, v.component, v.sysid, v.autopilot_component, key, self.boot)

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
        if self.loop is not None:
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
        self.deliver(msg)

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

    # -- send ----------------------------------------------------------------

    def send_heartbeat(self) -> None:
        with self._send_lock:
            self.conn.mav.heartbeat_send(
                mavlink.MAV_TYPE_ONBOARD_CONTROLLER, mavlink.MAV_AUTOPILOT_INVALID, 0, 0, mavlink.MAV_STATE_ACTIVE
            )

    def send(self, *msgs: Any, setpoint: bool = False) -> None:
        """Encoded messages, in order under one hold of the lock (thread-safe); `setpoint`: one
        setpoint, counted in `sent_setpoints`."""
        with self._send_lock:
            for msg in msgs:
                self.conn.mav.send(msg)
            if setpoint:
                self._sent += 1
