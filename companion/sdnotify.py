"""systemd readiness and watchdog notifications (sd_notify protocol, no libsystemd).

The service unit (systemd/bezier-companion@.service) is ``Type=notify`` with ``WatchdogSec=``:
systemd waits for ``READY=1`` and restarts the service when ``WATCHDOG=1`` stops arriving.
Outside systemd ($NOTIFY_SOCKET unset) every call is a cheap no-op, so callers never branch.

Usage (the service pings as its setpoint ticks are handled on the event loop)::

    notifier = Notifier()
    notifier.ready("streaming to autopilot")   # once Zenoh and MAVLink are up
    ...
    notifier.watchdog()                        # every tick; sends at most every interval/4
    ...
    notifier.stopping()
"""

from __future__ import annotations

import os
import socket
import time
from collections.abc import Callable, Mapping

_SENDS_PER_INTERVAL = 4.0


def _socket_address(raw: str) -> str | bytes:
    # A leading '@' names a Linux abstract-namespace socket: NUL byte on the wire.
    if raw.startswith("@"):
        return b"\0" + raw[1:].encode()
    return raw


def watchdog_interval(environ: Mapping[str, str] | None = None) -> float | None:
    """Seconds between watchdog deadlines requested by systemd, or None when not supervised.

    WATCHDOG_PID, when set, must name this process: a child that inherited the environment is
    not the one systemd is watching.
    """
    env = os.environ if environ is None else environ
    usec = env.get("WATCHDOG_USEC", "")
    if not usec:
        return None
    pid = env.get("WATCHDOG_PID", "")
    if pid and pid != str(os.getpid()):
        return None
    try:
        value = int(usec)
    except ValueError:
        return None
    return value / 1e6 if value > 0 else None


class Notifier:
    """Sends sd_notify datagrams to $NOTIFY_SOCKET; silent no-op when it is unset."""

    def __init__(
        self,
        environ: Mapping[str, str] | None = None,
        clock: Callable[[], float] = time.monotonic,
    ) -> None:
        env = os.environ if environ is None else environ
        raw = env.get("NOTIFY_SOCKET", "")
        self._address: str | bytes | None = _socket_address(raw) if raw else None
        self._sock: socket.socket | None = None
        if self._address is not None:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM | socket.SOCK_CLOEXEC)
        interval = watchdog_interval(env)
        self.interval: float | None = interval
        self._min_gap = interval / _SENDS_PER_INTERVAL if interval is not None else 0.0
        self._clock = clock
        self._last_ping = -float("inf")

    @property
    def enabled(self) -> bool:
        return self._sock is not None

    @property
    def watchdog_enabled(self) -> bool:
        return self._sock is not None and self.interval is not None

    def notify(self, *fields: str) -> bool:
        """Send one datagram of newline-separated KEY=VALUE fields; False if not sent."""
        if self._sock is None or self._address is None:
            return False
        try:
            self._sock.sendto("\n".join(fields).encode(), self._address)
        except OSError:
            # systemd gone or socket full: supervision is best-effort, never fatal to flight.
            return False
        return True

    def ready(self, status: str | None = None) -> bool:
        fields = ["READY=1", f"MAINPID={os.getpid()}"]
        if status is not None:
            fields.append(_status_field(status))
        return self.notify(*fields)

    def status(self, text: str) -> bool:
        return self.notify(_status_field(text))

    def stopping(self) -> bool:
        return self.notify("STOPPING=1")

    def watchdog(self, force: bool = False) -> bool:
        """Ping the watchdog; rate-limited so calling it at every setpoint tick is cheap."""
        if not self.watchdog_enabled:
            return False
        now = self._clock()
        if not force and now - self._last_ping < self._min_gap:
            return False
        sent = self.notify("WATCHDOG=1")
        if sent:
            self._last_ping = now
        return sent

    def close(self) -> None:
        if self._sock is not None:
            self._sock.close()
            self._sock = None

    def __enter__(self) -> Notifier:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _status_field(text: str) -> str:
    # The protocol is line-based: a newline inside STATUS would start a bogus field.
    return "STATUS=" + " ".join(text.splitlines())
