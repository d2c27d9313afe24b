"""A TCP link to the autopilot (ArduPilot SITL's SERIAL0 on port 5760, a TCP serial bridge),
or from it (`tcpin:`: the companion listens, and the autopilot or mavlink-router dials in), that
never blocks the thread reading or writing it.

pymavlink's `mavtcp` re-dials inside `recv()` and `write()` when the connection drops
(`autoreconnect`: up to 6 connects with a 1 s sleep between). Those calls run on the event loop
(reads, commands) and on the setpoint thread (writes): in the field, with ArduCopter SITL dead,
the loop froze ~4 s at a time, 11-17 times, and the setpoint process went on writing to the old
connection's descriptor after pymavlink had replaced it. Here `TcpConnection` never dials: a
`Dialler` thread does, with backoff, and hands each new connection over; a lost connection is
only reported. What the companion decides about a lost link is still decided from heartbeats
(companion/autopilot.py), as for UDP and serial links. For `tcpin:` a `Listener` thread takes the
dialler's place: it accepts one connection at a time and, after a loss, the next one (pymavlink's
`mavtcpin` switches descriptors inside `recv`, behind the event loop's back, and never notices a
connection that ended: a peer that dialled again was never heard).
"""

from __future__ import annotations

import logging
import os
import select
import socket
import threading
import time
from collections.abc import Callable
from typing import Any

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil

log = logging.getLogger("companion")

CONNECT_TIMEOUT = 2.0  # s for one connect: a host that does not answer must not hold the dialler long
FIRST_RETRY = 0.1  # s before dialling again after a failed connect; doubled up to ...
MAX_RETRY = 1.0  # ... this: a restarted SITL is found within a second of listening again
STABLE = 2.0  # s a connection must have lasted for the next loss to be dialled at once
SAY_EVERY = 30.0  # s between two log lines about failing connects in one outage


def tcp_address(url: str) -> tuple[str, int]:
    """(host, port) of a `tcp:HOST:PORT` (to dial) or `tcpin:HOST:PORT` (to listen on) URL."""
    kind = "tcpin" if url.startswith("tcpin:") else "tcp"
    host, sep, port = url.removeprefix(f"{kind}:").rpartition(":")
    if not sep or not port.isdigit():
        raise ValueError(f"[mavlink] url: expected {kind}:HOST:PORT, got {url!r}")
    return host or "127.0.0.1", int(port)


class TcpConnection(mavutil.mavfile):  # type: ignore[misc]
    """A pymavlink connection over TCP that never dials: `attach` gives it a connected socket,
    and when that connection ends (EOF, reset, broken pipe) it drops it and calls `on_lost`
    (from whichever thread saw it). Without a connection, reads return nothing and writes are
    dropped, as on a lost link."""

    def __init__(self, address: tuple[str, int], source_system: int, source_component: int) -> None:
        self.destination_addr = address
        self.port: socket.socket | None = None
        self.fd: int | None = None  # mavfile's: the connected socket's descriptor
        self.on_lost: Callable[[socket.socket, str], None] = lambda _sock, _why: None
        self._lock = threading.Lock()  # `port` is swapped on the loop, read by the setpoint thread
        super().__init__(None, f"tcp:{address[0]}:{address[1]}", source_system=source_system,
                         source_component=source_component)

    def attach(self, sock: socket.socket) -> None:
        """From now on read and write `sock` (connected, non-blocking)."""
        with self._lock:
            self.port = sock
            self.fd = sock.fileno()
        # nothing of a packet cut off by the old connection prefixes the new one's first
        mav = self.mav
        mav.buf, mav.buf_index, mav.expected_length = bytearray(), 0, mavutil.mavlink.HEADER_LEN_V1 + 2
        mav.have_prefix_error = False

    def _lose(self, sock: socket.socket, why: str) -> None:
        with self._lock:
            if self.port is not sock:
                return  # already reported
            self.port = None
            self.fd = None
        self.on_lost(sock, why)

    def recv(self, n: int | None = None) -> bytes:
        sock = self.port
        if sock is None:
            return b""
        if n is None:
            n = self.mav.bytes_needed()
        try:
            data = sock.recv(n)
        except (BlockingIOError, InterruptedError):
            return b""
        except OSError as exc:
            self._lose(sock, exc.strerror or str(exc))
            return b""
        if not data:
            self._lose(sock, "closed by the other end")
        return data

    def write(self, buf: bytes) -> None:
        sock = self.port
        if sock is None:
            return  # no connection: dropped, as a lost link drops it
        try:
            sock.send(buf)
        except (BlockingIOError, InterruptedError):
            pass  # the send buffer is full (the other end does not read): dropped, as pymavlink does
        except OSError as exc:
            self._lose(sock, exc.strerror or str(exc))

    def close(self) -> None:
        with self._lock:
            sock, self.port, self.fd = self.port, None, None
        if sock is not None:
            sock.close()


class Dialler:
    """Connects to `address` on a thread of its own whenever asked (`dial`), again and again
    with backoff until it succeeds, and hands the connected socket to `on_connected` (called on
    the dialler's thread). One connection at a time: it dials only when asked."""

    def __init__(self, address: tuple[str, int], on_connected: Callable[[socket.socket], None]) -> None:
        self.address = address
        self.on_connected = on_connected
        self.attempts = 0  # connects tried in the current outage
        self._want = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._connected_at = -float("inf")
        self._retry = 0.0

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="mavlink-tcp", daemon=True)
        self._thread.start()

    def dial(self) -> None:
        self._want.set()

    def stop(self) -> None:
        self._stop.set()
        self._want.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(CONNECT_TIMEOUT + 1.0)

    def _run(self) -> None:
        while True:
            self._want.wait()
            if self._stop.is_set():
                return
            self._want.clear()
            # a connection that ends as soon as it is made (a peer that takes one client and
            # drops the next) is not dialled again at once, forever
            if time.monotonic() - self._connected_at < STABLE:
                self._retry = min(max(2 * self._retry, FIRST_RETRY), MAX_RETRY)
                self._stop.wait(self._retry)
            else:
                self._retry = 0.0
            sock = self._connect()
            if sock is None:
                return  # stopped
            self._connected_at = time.monotonic()
            self.on_connected(sock)

    def _connect(self) -> socket.socket | None:
        self.attempts = 0
        retry, said = FIRST_RETRY, -float("inf")
        while not self._stop.is_set():
            self.attempts += 1
            try:
                sock = socket.create_connection(self.address, timeout=CONNECT_TIMEOUT)
            except OSError as exc:
                now = time.monotonic()
                if now - said >= SAY_EVERY:
                    said = now
                    log.warning("MAVLink TCP %s:%d: connect failed (%s); trying again every %.1f s at most, "
                                "off the event loop", *self.address, exc.strerror or exc, MAX_RETRY)
                self._stop.wait(retry)
                retry = min(2 * retry, MAX_RETRY)
                continue
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            return sock
        return None


class Listener:
    """`tcpin:`: listens on `address` and accepts connections on a thread of its own, one at a
    time, handing each to `on_connected` (called on the listener's thread); after a loss
    (`dial`, named as the dialler's) the next one. A peer dialling again while the old
    connection is still open waits in the backlog until that one ends. The port is bound in
    the constructor, so that a port in use is an error at start."""

    POLL = 0.2  # s between checks for stop while waiting for a connection

    def __init__(self, address: tuple[str, int], on_connected: Callable[[socket.socket], None]) -> None:
        self.address = address
        self.on_connected = on_connected
        self.attempts = 0  # connections accepted so far
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.sock.bind(address)
        self.sock.listen(1)
        self._want = threading.Event()
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def start(self) -> None:
        self._thread = threading.Thread(target=self._run, name="mavlink-tcpin", daemon=True)
        self._thread.start()

    def dial(self) -> None:
        """Accept the next connection (the first, or after a loss)."""
        self._want.set()

    def stop(self) -> None:
        self._stop.set()
        self._want.set()
        if self._thread is not None and self._thread is not threading.current_thread():
            self._thread.join(self.POLL + 1.0)
        self.sock.close()

    def _run(self) -> None:
        while True:
            self._want.wait()
            if self._stop.is_set():
                return
            self._want.clear()
            sock = self._accept()
            if sock is None:
                return  # stopped
            self.on_connected(sock)

    def _accept(self) -> socket.socket | None:
        while not self._stop.is_set():
            try:
                ready, _, _ = select.select([self.sock], [], [], self.POLL)
                if not ready:
                    continue
                sock, _ = self.sock.accept()
            except OSError:
                if self._stop.is_set():
                    return None
                time.sleep(self.POLL)  # a failed accept (the peer gave up): wait for the next
                continue
            self.attempts += 1
            sock.setblocking(False)
            sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            return sock
        return None


def describe(sock: Any) -> str:
    """`host:port -> host:port` of a connected socket, for the log."""
    try:
        here, there = sock.getsockname(), sock.getpeername()
    except OSError:
        return "?"
    return f"{here[0]}:{here[1]} -> {there[0]}:{there[1]}"
