"""`tcpin:` below the service: the URL, the waiting hint, and the Listener handing over one
connection at a time, the next only after a loss (companion.wire.tcp)."""

from __future__ import annotations

import queue
import socket

import pytest

from companion.autopilot import waiting_hint
from companion.wire.tcp import Listener, tcp_address


def test_tcpin_url_and_hint() -> None:
    assert tcp_address("tcpin:127.0.0.1:5770") == ("127.0.0.1", 5770)
    assert tcp_address("tcp:10.0.0.2:5760") == ("10.0.0.2", 5760)
    with pytest.raises(ValueError, match="tcpin:HOST:PORT"):
        tcp_address("tcpin:5770")
    hint = waiting_hint("tcpin:127.0.0.1:5770")
    assert hint.startswith("listening on TCP 127.0.0.1:5770") and "must connect here" in hint
    assert waiting_hint("tcp:127.0.0.1:5760").startswith("connecting to TCP")


def test_listener_accepts_one_connection_at_a_time_and_the_next_after_a_loss() -> None:
    got: queue.Queue[socket.socket] = queue.Queue()
    listener = Listener(("127.0.0.1", 0), got.put)
    port = listener.sock.getsockname()[1]
    listener.start()
    peers = []
    try:
        listener.dial()
        peers.append(socket.create_connection(("127.0.0.1", port), timeout=2))
        first = got.get(timeout=3)
        peers.append(socket.create_connection(("127.0.0.1", port), timeout=2))  # waits in the backlog
        with pytest.raises(queue.Empty):
            got.get(timeout=0.5)
        first.close()
        listener.dial()  # the link saw the first end: the next one
        second = got.get(timeout=3)
        assert second.getpeername() == peers[1].getsockname() and listener.attempts == 2
        second.close()
    finally:
        listener.stop()
        for p in peers:
            p.close()
    with pytest.raises(OSError):
        socket.create_connection(("127.0.0.1", port), timeout=1)  # stopped: the port is closed
