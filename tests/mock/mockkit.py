"""Helpers for the mock tests: free ports, a pymavlink client, a setpoint streamer, log access."""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Callable
from typing import Any

os.environ.setdefault("MAVLINK20", "1")

from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mav

from companion.wire import dialect
from sitl_mock import MockAutopilot

dialect.install()  # the PX4 flavour reports with EVENT (410), which pymavlink's common lacks

CUSTOM = mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED


def free_udp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def free_tcp_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Client:
    """A ground-station-like pymavlink client (sysid 255) with helpers for the tests."""

    def __init__(self, port: int, sysid: int = 255) -> None:
        self.conn: Any = mavutil.mavlink_connection(
            f"udpout:127.0.0.1:{port}", source_system=sysid, source_component=190, dialect="common"
        )
        self.conn.mav.srcSystem = sysid
        # Only the mock's own datagrams: under xdist a mock of another test may still stream to
        # a client port that closed, and the kernel can hand that port to this client (a foreign
        # "disarmed" heartbeat once ended a PX4 conformance test early).
        self.conn.port.connect(("127.0.0.1", port))
        self.mav: Any = self.conn.mav

    def hello(self, timeout: float = 5.0) -> Any:
        """Send heartbeats until the mock streams to us (it answers whoever sent it packets)."""
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            self.mav.heartbeat_send(mav.MAV_TYPE_GCS, mav.MAV_AUTOPILOT_INVALID, 0, 0, 0)
            msg = self.conn.recv_match(blocking=True, timeout=0.2)
            if msg is not None and msg.get_srcSystem() not in (254, 255):
                return msg
        raise AssertionError("nothing received from the mock")

    def wait(self, kind: str, timeout: float = 3.0, cond: Callable[[Any], bool] | None = None) -> Any:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            msg = self.conn.recv_match(type=kind, blocking=True, timeout=max(0.01, end - time.monotonic()))
            if msg is not None and (cond is None or cond(msg)):
                return msg
        return None

    def drain(self) -> None:
        while self.conn.recv_match(blocking=False) is not None:
            pass

    def command(self, command: int, *params: float, target: int = 1, timeout: float = 3.0) -> int:
        p = [*params, *([0.0] * (7 - len(params)))]
        self.drain()
        self.mav.command_long_send(target, 1, command, 0, *p)
        ack = self.wait("COMMAND_ACK", timeout, lambda m: m.command == command)
        assert ack is not None, f"no COMMAND_ACK for command {command}"
        return int(ack.result)

    def command_collect(self, command: int, *params: float, target: int = 1,
                        timeout: float = 3.0) -> tuple[int, list[Any]]:
        """Send a command; its result and every message that came before the ACK."""
        p = [*params, *([0.0] * (7 - len(params)))]
        self.drain()
        self.mav.command_long_send(target, 1, command, 0, *p)
        seen: list[Any] = []
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            msg = self.conn.recv_match(blocking=True, timeout=max(0.01, end - time.monotonic()))
            if msg is None:
                continue
            if msg.get_type() == "COMMAND_ACK" and msg.command == command:
                return int(msg.result), seen
            seen.append(msg)
        raise AssertionError(f"no COMMAND_ACK for command {command}")

    def collect(self, timeout: float, until: Callable[[Any], bool] | None = None) -> list[Any]:
        """Every message for `timeout` seconds, or up to and including the first `until` accepts."""
        seen: list[Any] = []
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            msg = self.conn.recv_match(blocking=True, timeout=max(0.01, end - time.monotonic()))
            if msg is None or msg.get_type() == "BAD_DATA":
                continue
            seen.append(msg)
            if until is not None and until(msg):
                break
        return seen

    def setpoint(self, x: float = 0.0, y: float = 0.0, z: float = -2.0, *, mask: int = 0b0000_1111_1111_1000,
                 frame: int = mav.MAV_FRAME_LOCAL_NED, vel: tuple[float, float, float] = (0, 0, 0),
                 acc: tuple[float, float, float] = (0, 0, 0), target: int = 1, yaw: float = 0.0) -> None:
        self.mav.set_position_target_local_ned_send(0, target, 1, frame, mask, x, y, z, *vel, *acc, yaw, 0.0)

    def mode(self, timeout: float = 3.0) -> str:
        hb = self.wait("HEARTBEAT", timeout, lambda m: m.get_srcSystem() != 255)
        assert hb is not None
        return str(mavutil.mode_string_v10(hb))

    def close(self) -> None:
        self.conn.close()


# Position only: ignore velocity, acceleration, yaw rate (bits 3..8, 11).
POS_ONLY = 0b0000_1101_1111_1000


class Streamer:
    """Streams setpoints from its own connection in a thread, as a companion would."""

    def __init__(self, port: int, rate_hz: float = 25.0, **setpoint: Any) -> None:
        import threading

        self.client = Client(port, sysid=254)
        self.rate_hz = rate_hz
        self.setpoint = setpoint
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            self.client.setpoint(**self.setpoint)
            self._stop.wait(1.0 / self.rate_hz)

    def stop(self) -> None:
        self._stop.set()
        self._thread.join()
        self.client.close()

    def __enter__(self) -> Streamer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.stop()


def events(msgs: list[Any]) -> list[dialect.EventInfo]:
    """The EVENT messages among `msgs`, decoded (id, level, PX4 name)."""
    return [dialect.decode_event(m) for m in msgs if m.get_type() == "EVENT"]


def records(mock: MockAutopilot, kind: str | None = None) -> list[dict[str, Any]]:
    """Log records so far (the mock keeps running)."""
    import json

    mock.log.flush()
    out = []
    assert mock.config.log_path is not None
    with open(mock.config.log_path, encoding="utf-8") as fh:
        for line in fh:
            try:
                rec = json.loads(line)
            except json.JSONDecodeError:
                break  # a line being written right now
            if kind is None or rec["type"] == kind:
                out.append(rec)
    return out


def wait_for(pred: Callable[[], Any], timeout: float = 5.0, step: float = 0.05) -> Any:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        value = pred()
        if value:
            return value
        time.sleep(step)
    return pred()
