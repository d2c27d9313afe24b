"""The demo's flights: publish a mission, run its mid-flight actions, wait for its end.

`fly` is the demo's Zenoh client loop (demo.run drives it, demo.analysis reads its outcome): it
puts the mission (and `start` on the ground), publishes each `Action` once its trigger holds,
shows live progress and collects the trajectories and events the companion published.
"""

from __future__ import annotations

import contextlib
import dataclasses
import queue
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.wire.frames import swap_points
from demo.rig import Peer, Rig, Sample

Trigger = Callable[[float, np.ndarray | None], bool]


@dataclass
class Action:
    """Something to publish mid-flight, once `when(seconds streaming, position ENU)` holds."""

    when: Trigger
    topic: str
    payload: dict[str, Any]
    label: str
    sent: float | None = None


def after(seconds: float) -> Trigger:
    return lambda t, pos: t >= seconds


@dataclass
class FlightOutcome:
    ok: bool
    reason: str
    t_put: float
    trajectories: list[Sample]  # every trajectory published after the mission was put
    t_stream: float | None
    t_done: float | None
    actions: list[Action]
    events: list[Sample]
    # (monotonic time, lead s) from the companion's status: what the setpoints were sampled ahead by
    leads: list[tuple[float, float]] = dataclasses.field(default_factory=list)


class Progress:
    def __init__(self) -> None:
        self.tty = sys.stdout.isatty()
        self._last = 0.0

    def show(self, text: str, force: bool = False) -> None:
        now = time.monotonic()
        if self.tty:
            sys.stdout.write("\r\033[K" + text)
            sys.stdout.flush()
        elif force or now - self._last >= 2.0:
            print("  " + text, flush=True)
            self._last = now

    def done(self) -> None:
        if self.tty:
            sys.stdout.write("\n")
            sys.stdout.flush()


def _status_line(name: str, status: Any, pos: np.ndarray | None, elapsed: float) -> str:
    st = status if isinstance(status, dict) else {}
    where = "" if pos is None else f"  ENU from home [{pos[0]:6.2f} {pos[1]:6.2f} {pos[2]:5.2f}] m"
    progress = st.get("progress")
    prog = f" {100 * progress:3.0f}%" if isinstance(progress, int | float) else ""
    err = st.get("tracking_error")
    track = f"  err {err:.2f} m" if isinstance(err, int | float) else ""
    return f"[{name}] t={elapsed:5.1f}s {st.get('state', '?'):<9}{prog}{where}{track}"


FAIL_EVENTS = {"rejected", "refused", "braking", "aborted"}
AIRBORNE = {"READY", "HOLDING", "STREAMING", "BRAKING"}


def fly(r: Rig, mission: dict[str, Any], actions: list[Action], timeout: float, progress: Progress) -> FlightOutcome:
    """Publish a mission (and `start` when on the ground), run the actions, wait for completion."""
    _drain(r.peer)
    status = r.peer.query("status") or {}
    t_put = r.peer.put("mission", mission)
    need_start = status.get("state") not in AIRBORNE
    trajectories: list[Sample] = []
    events: list[Sample] = []
    leads: list[tuple[float, float]] = []
    t_stream: float | None = None
    t_done: float | None = None
    reason = ""
    deadline = t_put + timeout
    name = mission["id"]
    while time.monotonic() < deadline and not reason and t_done is None:
        dead = r.check_alive()
        if dead:
            reason = dead
            break
        try:
            s: Sample | None = r.peer.samples.get(timeout=0.05)
        except queue.Empty:
            s = None
        if s is not None and s.topic == "trajectory":
            trajectories.append(s)
        elif s is not None and s.topic == "events":
            events.append(s)
            ev = s.data if isinstance(s.data, dict) else {}
            kind = str(ev.get("type", ""))
            if kind == "accepted" and ev.get("key") == "mission" and need_start:
                need_start = False
                r.peer.put("command", {"command": "start"})
                progress.show(f"[{name}] mission loaded; sent 'start' (arm, take off, fly)", force=True)
                progress.done()
            elif t_stream is None and (
                (kind == "state" and ev.get("to") == "STREAMING")
                # already streaming the previous mission: no state change, but this event
                or (kind == "accepted" and ev.get("mission") == name and "plan_ms" in ev)
            ):
                t_stream = s.mono
            elif kind == "mission_complete" and ev.get("mission") in (name, None):
                t_done = s.mono
            elif kind in FAIL_EVENTS or (kind == "state" and ev.get("to") in ("FAILSAFE", "PILOT", "IDLE")):
                reason = f"{kind}: {ev.get('message', '')}"
        now = time.monotonic()
        tel = r.peer.latest.get("telemetry")
        pos = _enu_position(tel.data if tel else None, r.home)
        if t_stream is not None:
            for a in actions:
                if a.sent is None and a.when(now - t_stream, pos):
                    a.sent = r.peer.put(a.topic, a.payload)
                    progress.show(f"[{name}] published {a.label}", force=True)
                    progress.done()
        st = r.peer.latest.get("status")
        if st is not None and isinstance(st.data, dict) and isinstance(st.data.get("lead_ms"), int | float) and (
                not leads or leads[-1][0] != st.mono):
            leads.append((st.mono, float(st.data["lead_ms"]) / 1000.0))
        progress.show(_status_line(name, st.data if st else None, pos, now - t_put))
    progress.done()
    if not reason and t_done is None:
        reason = f"timeout after {timeout:.0f} s"
    return FlightOutcome(not reason, reason, t_put, trajectories, t_stream, t_done, actions, events, leads)


def _enu_position(telemetry: Any, home: np.ndarray) -> np.ndarray | None:
    """Telemetry's local NED position as the demo's missions give positions: ENU from home."""
    if isinstance(telemetry, dict) and isinstance(telemetry.get("position"), list):
        with contextlib.suppress(ValueError, TypeError):
            return swap_points(np.asarray(telemetry["position"], dtype=float) - home)
    return None


def _drain(peer: Peer) -> None:
    with contextlib.suppress(queue.Empty):
        while True:
            peer.samples.get_nowait()
