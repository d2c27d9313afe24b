"""MAVLink endpoints: ``udpin:`` (server, replies to every sender), ``udpout:``, ``tcpin:``,
``tcpout:`` (a TCP client that dials, and dials again after a loss)."""

from __future__ import annotations

import socket
import time
from dataclasses import dataclass
from typing import Any

from pymavlink.dialects.v20 import common as mav

from .signing import setup_receive


@dataclass(frozen=True)
class Endpoint:
    kind: str  # udpin | udpout | tcpin | tcpout
    host: str
    port: int
    # udpout only: the local address to send from (and to answer on), as PX4 SITL's
    # offboard link does: bound to 14580, sending to 14540.
    bind: tuple[str, int] | None = None

    def __str__(self) -> str:
        suffix = f"@{self.bind[0]}:{self.bind[1]}" if self.bind else ""
        return f"{self.kind}:{self.host}:{self.port}{suffix}"


# PX4 SITL's offboard (Onboard-mode) MAVLink instance: listens on 14580, sends to 14540.
PX4_SITL_ENDPOINT = "udpout:127.0.0.1:14540@0.0.0.0:14580"
# tcpout: dial at start, as ArduPilot SITL's `--serial0 tcpclient:HOST:PORT` does
# (AP_HAL_SITL/UARTDriver.cpp _tcp_start_client), and again this long after a failed connect or a
# lost connection, as mavlink-router's TCP client endpoint does (its RetryTimeout, 5 s by
# default; shorter here, so that a dropped link comes back within PX4's COM_OF_LOSS_T). SITL
# itself exits when the first connect fails and never dials again after a loss (a restarted SITL
# dials anew): a mock that waits for its peer is kinder there, noted in the README.
TCP_REDIAL_S = 0.5
TCP_CONNECT_TIMEOUT_S = 0.2  # a blocking connect on the loop: short, loopback answers at once


def parse_endpoint(text: str) -> Endpoint:
    text, at, bind_text = text.partition("@")
    bind: tuple[str, int] | None = None
    if at:
        bhost, bsep, bport = bind_text.rpartition(":")
        if not text.lower().startswith("udpout:") or not bsep or not bport.isdigit():
            raise ValueError(f"--endpoint: a bind address (@HOST:PORT) goes with udpout only, got {text + at + bind_text!r}")
        bind = (bhost or "0.0.0.0", int(bport))
    ep = _parse_plain(text)
    return Endpoint(ep.kind, ep.host, ep.port, bind) if bind else ep


def _parse_plain(text: str) -> Endpoint:
    kind, sep, rest = text.partition(":")
    kind = kind.lower()
    aliases = {"udp": "udpin", "udpin": "udpin", "udpout": "udpout", "tcpin": "tcpin", "tcpout": "tcpout"}
    host, sep2, port = rest.rpartition(":")
    if not sep or kind not in aliases or not sep2 or not port.isdigit():
        raise ValueError(
            f"--endpoint: expected udpin:HOST:PORT, udpout:HOST:PORT, tcpin:HOST:PORT or tcpout:HOST:PORT, got {text!r}"
        )
    if aliases[kind] == "tcpout" and not host:
        raise ValueError(f"--endpoint: tcpout needs the host to dial, got {text!r}")
    return Endpoint(aliases[kind], host or "0.0.0.0", int(port))


class _Capture:
    """File-like sink so that pymavlink's MAVLink.send() does framing and sequencing."""

    def __init__(self) -> None:
        self.data = b""

    def write(self, data: bytes) -> None:
        self.data = bytes(data)


class Encoder:
    def __init__(self, sysid: int, compid: int) -> None:
        self._sink = _Capture()
        self.mav = mav.MAVLink(self._sink, srcSystem=sysid, srcComponent=compid)

    def encode(self, msg: Any) -> bytes:
        self.mav.send(msg)
        return self._sink.data


def new_parser(signing_key: bytes | None = None) -> Any:
    parser = mav.MAVLink(None)
    parser.robust_parsing = True
    if signing_key is not None:
        setup_receive(parser, signing_key)
    return parser


class Link:
    """One endpoint; ``poll_sockets`` are selected by the owner, which calls ``read``."""

    def __init__(self, endpoint: Endpoint) -> None:
        self.endpoint = endpoint
        self.peers: list[Any] = []  # udp addresses or tcp sockets
        self.parsers: dict[Any, Any] = {}
        self.signing_key: bytes | None = None  # set: commands and setpoints must be signed with it
        self.rejected = 0  # packets dropped for a missing or wrong signature
        self.connects = 0  # tcpout: connections made so far
        self._dial_at = 0.0  # tcpout: monotonic time of the next connect attempt
        # the listening (tcpin) or datagram socket; tcpout has none: its connection is its one peer
        self.sock: socket.socket | None = None
        self.address: tuple[str, int] = (endpoint.host, endpoint.port)
        if endpoint.kind == "tcpout":
            return
        if endpoint.kind == "tcpin":
            sock = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            sock.bind((endpoint.host, endpoint.port))
            sock.listen(4)
        else:
            sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            if endpoint.kind == "udpin":
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                sock.bind((endpoint.host, endpoint.port))
            else:
                if endpoint.bind is not None:
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                    sock.bind(endpoint.bind)
                self.peers.append((endpoint.host, endpoint.port))
        sock.setblocking(False)
        self.sock = sock
        self.address = sock.getsockname()

    def poll_sockets(self) -> list[socket.socket]:
        if self.sock is None:
            return list(self.peers)
        if self.endpoint.kind == "tcpin":
            return [self.sock, *self.peers]
        return [self.sock]

    def maintain(self, now: float) -> bool:
        """tcpout: dial when not connected and the retry time has come; True when it connected."""
        if self.endpoint.kind != "tcpout" or self.peers or now < self._dial_at:
            return False
        self._dial_at = now + TCP_REDIAL_S
        try:
            conn = socket.create_connection((self.endpoint.host, self.endpoint.port), timeout=TCP_CONNECT_TIMEOUT_S)
        except OSError:
            return False
        conn.setblocking(False)
        conn.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
        self.peers.append(conn)
        self.connects += 1
        return True

    def drop(self) -> int:
        """Close every TCP connection (the other end sees it end, as when a router or cable drops
        it); a tcpout link dials again TCP_REDIAL_S later. The number closed."""
        conns = [p for p in self.peers if isinstance(p, socket.socket)]
        for conn in conns:
            self._lost(conn)
        return len(conns)

    def _lost(self, conn: socket.socket) -> None:
        self.peers.remove(conn)
        self.parsers.pop(conn, None)
        conn.close()
        self._dial_at = time.monotonic() + TCP_REDIAL_S

    def read(self, sock: socket.socket) -> list[tuple[Any, bytes]]:
        """Raw chunks with their peer key; new UDP senders become reply peers."""
        out: list[tuple[Any, bytes]] = []
        if self.endpoint.kind in ("tcpin", "tcpout"):
            if self.sock is not None and sock is self.sock:
                try:
                    conn, _ = self.sock.accept()
                except BlockingIOError:
                    return out
                conn.setblocking(False)
                self.peers.append(conn)
                return out
            try:
                data = sock.recv(65536)
            except (BlockingIOError, InterruptedError):
                return out
            except OSError:
                data = b""
            if not data:
                self._lost(sock)
                return out
            return [(sock, data)]
        assert self.sock is not None  # a datagram endpoint
        for _ in range(64):
            try:
                data, addr = self.sock.recvfrom(65536)
            except (BlockingIOError, InterruptedError):
                break
            except OSError:
                # ICMP port unreachable from a udpout peer that is not up yet.
                break
            if (self.endpoint.kind == "udpin" or self.endpoint.bind is not None) and addr not in self.peers:
                self.peers.append(addr)
            out.append((addr, data))
        return out

    def parse(self, peer: Any, data: bytes) -> list[Any]:
        parser = self.parsers.get(peer)
        if parser is None:
            parser = self.parsers[peer] = new_parser(self.signing_key)
        before = parser.signing.reject_count + parser.signing.badsig_count
        try:
            msgs = parser.parse_buffer(data)
        except mav.MAVError:
            msgs = []
        after = parser.signing.reject_count + parser.signing.badsig_count
        self.rejected += after - before
        return [m for m in (msgs or []) if m.get_type() != "BAD_DATA"]

    def send(self, data: bytes) -> None:
        for peer in list(self.peers):
            try:
                if isinstance(peer, socket.socket):
                    peer.sendall(data)
                elif self.sock is not None:
                    self.sock.sendto(data, peer)
            except (BlockingIOError, InterruptedError):
                pass
            except OSError:
                if isinstance(peer, socket.socket):
                    self._lost(peer)

    def close(self) -> None:
        for peer in self.peers:
            if isinstance(peer, socket.socket):
                peer.close()
        if self.sock is not None:
            self.sock.close()
