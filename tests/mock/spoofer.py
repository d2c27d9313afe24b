"""A MAVLink spoofer for the peer-authentication tests: raw pymavlink on its own UDP socket,
claiming the autopilot's ids (or others), and counting what the companion sends it."""

from __future__ import annotations

import socket
import time
from typing import Any

from pymavlink.dialects.v20 import common as mav

CUSTOM = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED
ARMED = mav.MAV_MODE_FLAG_SAFETY_ARMED
PX4_OFFBOARD = 6 << 16  # PX4 custom_mode: main mode in bits 16-23


class Spoofer:
    """Sends from its own socket (`bind`: a chosen local address, shared with SO_REUSEADDR);
    `received()` drains what came back, by message type."""

    def __init__(self, port: int, sysid: int = 1, compid: int = 1, bind: tuple[str, int] | None = None) -> None:
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        if bind is not None:
            self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self.sock.bind(bind)
        self.sock.setblocking(False)
        self.dest = ("127.0.0.1", port)
        self.mav = mav.MAVLink(self, srcSystem=sysid, srcComponent=compid)
        self.parser = mav.MAVLink(None)
        self.parser.robust_parsing = True
        self.counts: dict[str, int] = {}

    def write(self, buf: bytes) -> None:  # the MAVLink encoder's file
        self.sock.sendto(buf, self.dest)

    def heartbeat(self, armed: bool, custom_mode: int = PX4_OFFBOARD, n: int = 1, every: float = 0.05) -> None:
        for _ in range(n):
            self.mav.heartbeat_send(mav.MAV_TYPE_QUADROTOR, mav.MAV_AUTOPILOT_PX4, CUSTOM | (ARMED if armed else 0),
                                    custom_mode, mav.MAV_STATE_ACTIVE)
            time.sleep(every)

    def received(self) -> dict[str, int]:
        while True:
            try:
                data = self.sock.recv(65535)
            except (BlockingIOError, InterruptedError, ConnectionRefusedError):
                break
            for m in self.parser.parse_buffer(data) or []:
                kind = m.get_type()
                self.counts[kind] = self.counts.get(kind, 0) + 1
        return dict(self.counts)

    def close(self) -> None:
        self.sock.close()


def local_address(sock: Any) -> tuple[str, int]:
    host, port = sock.getsockname()[:2]
    return ("127.0.0.1" if host == "0.0.0.0" else host, int(port))
