"""`python -m demo.tap`: the demo's MAVLink tap for flying against a real autopilot
(`python -m demo --autopilot-url URL`).

Sits between the companion (which sends to --listen over UDP) and the autopilot at URL, forwards
every byte both ways unchanged, and writes a flight log in sitl_mock's format (JSON Lines, on
this machine's time.monotonic(), which the demo shares) so that demo.analysis reads it as it
reads the mock's:

- "state": the autopilot's LOCAL_POSITION_NED, its own estimate, not the truth. Its time is the
  autopilot's time_boot_ms mapped onto time.monotonic() by the lower envelope of the arrivals
  over STATE_CLOCK_WINDOW_S, sloped as the autopilot's clock runs against ours there
  (`state_time`): transport jitter out, and a simulator that runs slower than real time
  followed (PX4 SIH in lockstep ran at 0.69-0.98 x real time on a loaded 2-core machine; a plain
  sliding minimum then put states up to 0.6 s early), so a state carries the time it
  describes, not when it arrived.
- "setpoint": each SET_POSITION_TARGET_LOCAL_NED the companion sent, at the time it was
  forwarded (what the autopilot received, not what it applied: a real autopilot does not say).
- "truth": HIL_STATE_QUATERNION if the autopilot sends it (PX4 SIH's ground truth, on request),
  at its arrival: the message carries no time of its own there.
- "home": HOME_POSITION, global and local (to put the truth's latitude, longitude and altitude
  in the local frame; PX4 sends it every few seconds, GPS_GLOBAL_ORIGIN only once at boot).
- "mode": the autopilot's HEARTBEAT whenever its mode or armed state changes.
"""

from __future__ import annotations

import argparse
import collections
import json
import select
import signal
import socket
import sys
import time
from types import FrameType
from typing import Any, TextIO

import numpy as np
from pymavlink.dialects.v20 import ardupilotmega as mav  # MAVLink 2 framing, the superset dialect

STATE_CLOCK_WINDOW_S = 0.5
POS_IGNORED = 0b111  # type_mask bits: x, y, z ignored
FLUSH_EVERY_S = 0.2
UDP_CHUNK = 1400  # bytes per datagram when a TCP read is passed on over UDP


class Autopilot:
    """The autopilot's end of the tap: udpin (listen, answer the last sender), udpout (send to
    it), tcp (dial, re-dial after a loss) or tcpin (accept one connection at a time)."""

    def __init__(self, url: str) -> None:
        kind, _, rest = url.partition(":")
        host, sep, port = rest.rpartition(":")
        if kind not in ("udpin", "udp", "udpout", "tcp", "tcpin") or not sep or not port.isdigit():
            raise ValueError(f"autopilot URL: expected udpin:, udpout:, tcp: or tcpin:HOST:PORT, got {url!r}")
        self.kind = "udpin" if kind == "udp" else kind
        self.address = (host or "127.0.0.1", int(port))
        self.peer: tuple[str, int] | None = self.address if self.kind == "udpout" else None
        self.server: socket.socket | None = None
        self.sock: socket.socket | None = None
        if self.kind in ("udpin", "udpout"):
            self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
            self.sock.bind(self.address if self.kind == "udpin" else ("0.0.0.0", 0))
        elif self.kind == "tcpin":
            self.server = socket.socket(socket.AF_INET, socket.SOCK_STREAM)
            self.server.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self.server.bind(self.address)
            self.server.listen(1)
        self._next_dial = 0.0

    def readable(self) -> list[socket.socket]:
        if self.sock is None and self.kind == "tcp" and time.monotonic() >= self._next_dial:
            try:
                self.sock = socket.create_connection(self.address, timeout=1.0)
                self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            except OSError:
                self._next_dial = time.monotonic() + 0.5
        return [s for s in (self.sock, self.server) if s is not None]

    def receive(self, ready: list[socket.socket]) -> bytes:
        if self.server is not None and self.server in ready:
            conn, _ = self.server.accept()
            if self.sock is not None:
                self.sock.close()
            self.sock = conn
            self.sock.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
            return b""
        if self.sock is None or self.sock not in ready:
            return b""
        if self.kind in ("udpin", "udpout"):
            data, addr = self.sock.recvfrom(65536)
            if self.kind == "udpin":
                self.peer = addr
            return data
        try:
            data = self.sock.recv(65536)
        except OSError:
            data = b""
        if not data:  # the connection ended: dial (or accept) again
            self.sock.close()
            self.sock = None
        return data

    def send(self, data: bytes) -> None:
        if self.sock is None:
            return
        try:
            if self.kind in ("udpin", "udpout"):
                if self.peer is not None:
                    self.sock.sendto(data, self.peer)
            else:
                self.sock.sendall(data)
        except OSError:
            pass  # a lost link: the companion sees it as the autopilot's silence


def state_time(arrivals: collections.deque[tuple[float, float]]) -> float:
    """Our time of the newest of `arrivals` ((arrival on our clock, time on the autopilot's),
    oldest first): the earliest any of them says it could have been, each carried forward at
    the rate the autopilot's clock ran against ours over the window (a least-squares slope; 1
    over less than a third of the window)."""
    ours = np.array([a for a, _ in arrivals])
    theirs = np.array([b for _, b in arrivals])
    rate = 1.0
    if theirs[-1] - theirs[0] >= STATE_CLOCK_WINDOW_S / 3:
        rate = float(np.polyfit(theirs, ours, 1)[0])
    return float(np.min(ours + (theirs[-1] - theirs) * rate))


class FlightLog:
    """The records (module docstring); flushed every FLUSH_EVERY_S for the demo to read."""

    def __init__(self, out: TextIO) -> None:
        self.out = out
        self.arrivals: collections.deque[tuple[float, float]] = collections.deque()  # (ours, autopilot's)
        self.last_mode: tuple[int, int] | None = None
        self.last_flush = time.monotonic()

    def write(self, rec: dict[str, Any]) -> None:
        self.out.write(json.dumps(rec, separators=(",", ":")) + "\n")

    def from_companion(self, msg: Any, now: float) -> None:
        if msg.get_type() == "SET_POSITION_TARGET_LOCAL_NED":
            pos = None if msg.type_mask & POS_IGNORED else [msg.x, msg.y, msg.z]
            self.write({"type": "setpoint", "t": now, "applied": True, "pos": pos, "vel": [msg.vx, msg.vy, msg.vz],
                        "acc": [msg.afx, msg.afy, msg.afz], "time_boot_ms": msg.time_boot_ms})

    def from_autopilot(self, msg: Any, now: float) -> None:
        kind = msg.get_type()
        if kind == "LOCAL_POSITION_NED":
            boot = msg.time_boot_ms / 1000.0
            self.arrivals.append((now, boot))
            while self.arrivals[0][0] < now - STATE_CLOCK_WINDOW_S:
                self.arrivals.popleft()
            self.write({"type": "state", "t": state_time(self.arrivals), "arr": now, "tb": boot,
                        "pos": [msg.x, msg.y, msg.z], "vel": [msg.vx, msg.vy, msg.vz]})
        elif kind == "HIL_STATE_QUATERNION":
            self.write({"type": "truth", "t": now, "lat": msg.lat * 1e-7, "lon": msg.lon * 1e-7,
                        "alt": msg.alt / 1000.0, "vel": [msg.vx / 100.0, msg.vy / 100.0, msg.vz / 100.0]})
        elif kind == "HOME_POSITION":
            self.write({"type": "home", "t": now, "lat": msg.latitude * 1e-7, "lon": msg.longitude * 1e-7,
                        "alt": msg.altitude / 1000.0, "pos": [msg.x, msg.y, msg.z]})
        elif kind == "HEARTBEAT" and msg.autopilot != mav.MAV_AUTOPILOT_INVALID:
            mode = (int(msg.custom_mode), int(msg.base_mode & mav.MAV_MODE_FLAG_SAFETY_ARMED))
            if mode != self.last_mode:
                self.last_mode = mode
                self.write({"type": "mode", "t": now, "custom_mode": mode[0], "armed": bool(mode[1])})

    def maybe_flush(self, now: float) -> None:
        if now - self.last_flush >= FLUSH_EVERY_S:
            self.out.flush()
            self.last_flush = now


def run(listen: tuple[str, int], url: str, log_path: str) -> int:
    companion = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    companion.bind(listen)
    autopilot = Autopilot(url)
    up, down = mav.MAVLink(None), mav.MAVLink(None)
    up.robust_parsing = down.robust_parsing = True
    peer: tuple[str, int] | None = None  # the companion's address, once it has sent
    stopping = []

    def on_signal(signum: int, frame: FrameType | None) -> None:
        stopping.append(signum)

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    print(f"demo.tap: companion -> udp {listen[0]}:{listen[1]}, autopilot {url}, log {log_path}", flush=True)
    with open(log_path, "w", encoding="utf-8") as fh:
        log = FlightLog(fh)
        while not stopping:
            try:
                ready, _, _ = select.select([companion, *autopilot.readable()], [], [], 0.2)
            except InterruptedError:
                continue
            now = time.monotonic()
            if companion in ready:
                data, peer = companion.recvfrom(65536)
                autopilot.send(data)
                for msg in up.parse_buffer(data) or []:
                    log.from_companion(msg, now)
            data = autopilot.receive(ready)
            if data:
                if peer is not None:
                    for i in range(0, len(data), UDP_CHUNK):
                        companion.sendto(data[i:i + UDP_CHUNK], peer)
                for msg in down.parse_buffer(data) or []:
                    log.from_autopilot(msg, now)
            log.maybe_flush(now)
    return 0


def _host_port(text: str) -> tuple[str, int]:
    host, _, port = text.rpartition(":")
    return host or "127.0.0.1", int(port)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m demo.tap", description=__doc__.splitlines()[0])
    p.add_argument("--listen", type=_host_port, required=True, metavar="HOST:PORT",
                   help="UDP address the companion sends to (its [mavlink] url udpout:HOST:PORT)")
    p.add_argument("--autopilot", required=True, metavar="URL", help="udpin:, udpout:, tcp: or tcpin:HOST:PORT")
    p.add_argument("--log", required=True, metavar="FILE.jsonl")
    args = p.parse_args(argv)
    try:
        return run(args.listen, args.autopilot, args.log)
    except (ValueError, OSError) as exc:
        print(f"demo.tap: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
