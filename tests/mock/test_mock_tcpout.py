"""`tcpout:HOST:PORT`: the mock dials a TCP listener, as ArduPilot SITL's `--serial0
tcpclient:HOST:PORT` does, and dials again after the connection is lost, as mavlink-router's TCP
client endpoint does (sitl_mock.transport.TCP_REDIAL_S). The client here is a plain listening
socket parsed with pymavlink (pymavlink's own `tcpin` never notices a connection that ended)."""

from __future__ import annotations

import select
import socket
import time
from typing import Any

import pytest
from mockkit import free_tcp_port
from pymavlink.dialects.v20 import common as mav

from sitl_mock import ControlClient, MockAutopilot, MockConfig
from sitl_mock.transport import parse_endpoint


def _accept(listener: socket.socket, timeout: float) -> socket.socket:
    ready, _, _ = select.select([listener], [], [], timeout)
    assert ready, "the mock did not dial"
    conn, _ = listener.accept()
    conn.settimeout(0.2)
    return conn


def _first(conn: socket.socket, timeout: float = 3.0, kind: str = "HEARTBEAT") -> Any:
    parser = mav.MAVLink(None)
    parser.robust_parsing = True
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            data = conn.recv(4096)
        except TimeoutError:
            continue
        if not data:
            return None
        for msg in parser.parse_buffer(data) or []:
            if msg.get_type() == kind:
                return msg
    return None


def _closed(conn: socket.socket, timeout: float = 3.0) -> bool:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        try:
            if conn.recv(4096) == b"":
                return True
        except TimeoutError:
            continue
        except OSError:
            return True
    return False


def test_the_mock_dials_waits_for_a_listener_and_dials_again_after_a_drop(tmp_path: Any) -> None:
    port = free_tcp_port()
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=[f"tcpout:127.0.0.1:{port}"], control="127.0.0.1:0",
                                    log_path=str(tmp_path / "f.jsonl"))).start()
    listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
    try:
        time.sleep(0.6)  # nothing listens yet: the mock tries again (SITL would have exited)
        listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        listener.bind(("127.0.0.1", port))
        listener.listen(1)
        first = _accept(listener, 3.0)
        hb = _first(first)
        assert hb is not None and hb.autopilot == mav.MAV_AUTOPILOT_PX4
        # commands over the dialled connection are answered on it
        sender = mav.MAVLink(None, srcSystem=255, srcComponent=190)
        first.sendall(sender.command_long_encode(1, 1, mav.MAV_CMD_REQUEST_MESSAGE, 0,
                                                 mav.MAVLINK_MSG_ID_HOME_POSITION, 0, 0, 0, 0, 0, 0).pack(sender))
        assert _first(first, kind="COMMAND_ACK") is not None
        assert mock.control_address is not None
        with ControlClient(*mock.control_address) as ctl:
            assert ctl.drop_tcp()["closed"] == 1
        assert _closed(first), "the dropped connection did not end"
        first.close()
        second = _accept(listener, 3.0)  # dialled again
        assert _first(second) is not None
        second.close()  # the mock sees the connection end from our side too, and dials again
        _accept(listener, 3.0).close()
    finally:
        listener.close()
        mock.stop()
    records = [r for r in _log(tmp_path / "f.jsonl") if r.get("event") == "tcp_connected"]
    assert [r["connects"] for r in records][:3] == [1, 2, 3], records


def _log(path: Any) -> list[dict[str, Any]]:
    import json

    out = []
    with open(path, encoding="utf-8") as fh:
        for line in fh:
            try:
                out.append(json.loads(line))
            except json.JSONDecodeError:
                break
    return out


def test_tcpout_endpoint_parsing() -> None:
    ep = parse_endpoint("tcpout:127.0.0.1:5760")
    assert (ep.kind, ep.host, ep.port) == ("tcpout", "127.0.0.1", 5760)
    with pytest.raises(ValueError, match="tcpout needs the host"):
        parse_endpoint("tcpout::5760")
