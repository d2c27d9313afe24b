"""Control socket: JSON lines over TCP, one reply line per request.

The server side is polled from the mock's single select loop, so handlers run on the
simulation thread and need no locking.
"""

from __future__ import annotations

import json
import socket
from collections.abc import Callable
from typing import Any

Handler = Callable[[dict[str, Any]], dict[str, Any]]


def parse_hostport(text: str, field_name: str) -> tuple[str, int]:
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit():
        raise ValueError(f"{field_name}: expected HOST:PORT, got {text!r}")
    return host or "127.0.0.1", int(port)


class ControlServer:
    def __init__(self, host: str, port: int, handler: Handler) -> None:
        self.listener = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        self.listener.bind((host, port))
        self.listener.listen(8)
        self.listener.setblocking(False)
        self.address: tuple[str, int] = self.listener.getsockname()
        self.handler = handler
        self.clients: dict[socket.socket, bytearray] = {}

    def sockets(self) -> list[socket.socket]:
        return [self.listener, *self.clients]

    def handle_readable(self, sock: socket.socket) -> None:
        if sock is self.listener:
            try:
                conn, _ = self.listener.accept()
            except BlockingIOError:
                return
            conn.setblocking(False)
            self.clients[conn] = bytearray()
            return
        try:
            data = sock.recv(65536)
        except (BlockingIOError, InterruptedError):
            return
        except OSError:
            data = b""
        if not data:
            self._drop(sock)
            return
        buf = self.clients[sock]
        buf.extend(data)
        while b"\n" in buf:
            line, _, rest = bytes(buf).partition(b"\n")
            buf[:] = rest
            if line.strip():
                self._reply(sock, self._dispatch(line))

    def _dispatch(self, line: bytes) -> dict[str, Any]:
        try:
            request = json.loads(line)
        except json.JSONDecodeError as exc:
            return {"ok": False, "error": f"invalid JSON: {exc.msg} at column {exc.colno}"}
        if not isinstance(request, dict) or not isinstance(request.get("cmd"), str):
            return {"ok": False, "error": "request must be an object with a string field 'cmd'"}
        try:
            return self.handler(request)
        except (ValueError, KeyError, TypeError) as exc:
            return {"ok": False, "error": str(exc)}

    def _reply(self, sock: socket.socket, reply: dict[str, Any]) -> None:
        try:
            sock.setblocking(True)
            sock.sendall((json.dumps(reply) + "\n").encode())
            sock.setblocking(False)
        except OSError:
            self._drop(sock)

    def _drop(self, sock: socket.socket) -> None:
        self.clients.pop(sock, None)
        sock.close()

    def close(self) -> None:
        for sock in list(self.clients):
            self._drop(sock)
        self.listener.close()


class ControlClient:
    """Blocking client for the control socket."""

    def __init__(self, host: str, port: int, timeout: float = 5.0) -> None:
        self.sock = socket.create_connection((host, port), timeout=timeout)
        self._buf = bytearray()

    def request(self, cmd: str, **fields: Any) -> dict[str, Any]:
        self.sock.sendall((json.dumps({"cmd": cmd, **fields}) + "\n").encode())
        while b"\n" not in self._buf:
            chunk = self.sock.recv(65536)
            if not chunk:
                raise ConnectionError("control socket closed by the mock")
            self._buf.extend(chunk)
        line, _, rest = bytes(self._buf).partition(b"\n")
        self._buf[:] = rest
        reply: dict[str, Any] = json.loads(line)
        return reply

    def set_mode(self, mode: str) -> dict[str, Any]:
        return self.request("set_mode", mode=mode)

    def pause_link(self, seconds: float) -> dict[str, Any]:
        return self.request("pause_link", seconds=seconds)

    def drop(self, fraction: float) -> dict[str, Any]:
        return self.request("drop", fraction=fraction)

    def latency(self, ms: float) -> dict[str, Any]:
        return self.request("latency", ms=ms)

    def reboot(self) -> dict[str, Any]:
        return self.request("reboot")

    def reject_arming(self, value: bool = True) -> dict[str, Any]:
        return self.request("reject_arming", value=value)

    def rc(self, throttle: int | None) -> dict[str, Any]:
        """ArduPilot: the throttle pwm the autopilot receives from now on; None: RC lost."""
        return self.request("rc", throttle=throttle)

    def drop_tcp(self) -> dict[str, Any]:
        """Close the mock's TCP connections (tcpin and tcpout); a tcpout endpoint dials again."""
        return self.request("drop_tcp")

    def state(self) -> dict[str, Any]:
        return self.request("state")

    def stop(self) -> dict[str, Any]:
        return self.request("stop")

    def close(self) -> None:
        self.sock.close()

    def __enter__(self) -> ControlClient:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
