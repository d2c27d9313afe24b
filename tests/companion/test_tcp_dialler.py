"""The TCP link's dialler (companion/wire/tcp.py) against a real listening socket: an autopilot
port that takes every connection and drops it at once (a SITL whose one client slot is taken, a
bridge that cannot reach its serial port) is dialled again with backoff, not in a busy loop, and
the event loop is never held up meanwhile."""

from __future__ import annotations

import asyncio
import itertools
import socket
import threading
import time

from companion.config import config_from_dict
from companion.wire.mavlink import MavlinkLink
from companion.wire.tcp import MAX_RETRY, TcpConnection

WATCH = 3.0  # s of dropped connections watched


def _dropping_server(accepted: list[float], stop: threading.Event) -> tuple[socket.socket, threading.Thread]:
    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(8)
    server.settimeout(0.05)

    def serve() -> None:
        while not stop.is_set():
            try:
                conn, _ = server.accept()
            except TimeoutError:
                continue
            accepted.append(time.monotonic())
            conn.close()

    thread = threading.Thread(target=serve, daemon=True)
    thread.start()
    return server, thread


def test_a_port_that_drops_every_connection_is_dialled_again_with_backoff() -> None:
    accepted: list[float] = []
    stop = threading.Event()
    server, thread = _dropping_server(accepted, stop)
    port = server.getsockname()[1]

    async def go() -> float:
        link = MavlinkLink(config_from_dict({"mavlink": {"url": f"tcp:127.0.0.1:{port}"}}))
        link.open(asyncio.get_running_loop())
        assert isinstance(link.conn, TcpConnection)
        longest, last, end = 0.0, time.monotonic(), time.monotonic() + WATCH
        try:
            while time.monotonic() < end:
                link.send_heartbeat()  # with or without a connection: never raises, never waits
                await asyncio.sleep(0.01)
                now = time.monotonic()
                longest, last = max(longest, now - last), now
        finally:
            link.close()
        return longest

    try:
        longest = asyncio.run(go())
    finally:
        stop.set()
        thread.join(2.0)
        server.close()
    # backoff 0.1, 0.2, 0.4, 0.8, then MAX_RETRY apart: ~6 in 3 s; re-dialled at once, thousands
    assert 3 <= len(accepted) <= 2 + WATCH / 0.1, f"{len(accepted)} connections in {WATCH} s"
    late = [b - a for a, b in itertools.pairwise(accepted[4:])]
    assert all(gap >= 0.5 * MAX_RETRY for gap in late), late
    assert longest < 0.5, f"the event loop was held up {longest:.2f} s"
