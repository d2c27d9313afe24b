"""Black-box helpers for the operator-sequence tests: a Rig with a few extra powers, and
checks on what the companion publishes, read from the JSON alone (no planner_core import,
so the checks do not share the code they check).

Published trajectories are degree-9 Bézier segments in NED on the companion's time base
(seconds since it last took control). A mission waypoint appears in a plan as a segment
junction (a segment's first control point, or the last one of the last segment).
"""

from __future__ import annotations

import contextlib
import json
import math
import os
import subprocess
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from math import comb
from typing import Any

import numpy as np
from e2e_rig import REPO, Rig

DEGREE = 9
_BINOM = np.array([comb(DEGREE, k) for k in range(DEGREE + 1)], dtype=float)
# The rig's [planner.bounds] (per axis, symmetric) and radius; stops and holds use them too.
VELOCITY_BOUND = 3.0
ACCELERATION_BOUND = 4.0
WAYPOINT_TOL = 1e-6
CERT_PIECES = 3  # the planner certifies each hodograph on 3 de Casteljau pieces (issue 12)


def _pieces(pts: np.ndarray, pieces: int = CERT_PIECES) -> np.ndarray:
    """Control points of the curve's restrictions to [i/p, (i+1)/p], one piece after the other
    (de Casteljau splits): their hull holds the curve, tighter than the whole polygon's."""
    out = []
    rest = np.asarray(pts, dtype=float)
    for i in range(pieces - 1):
        u = 1.0 / (pieces - i)
        work, left, right = rest, [rest[0]], [rest[-1]]
        for _ in range(len(rest) - 1):
            work = (1.0 - u) * work[:-1] + u * work[1:]
            left.append(work[0])
            right.append(work[-1])
        out.append(np.array(left))
        rest = np.array(right[::-1])
    out.append(rest)
    return np.concatenate(out)


@dataclass(frozen=True)
class Plan:
    """One published trajectory, as received."""

    received: float  # time.monotonic() at the subscriber (same clock as the companion's)
    times: np.ndarray  # (n + 1,)
    ctrl: np.ndarray  # (n, 10, 3)
    corridors: list[dict[str, Any] | None]

    @classmethod
    def from_message(cls, received: float, obj: dict[str, Any]) -> Plan:
        segs = obj["segments"]
        times = np.array([s["t0"] for s in segs] + [segs[-1]["t1"]], dtype=float)
        ctrl = np.array([s["control_points"] for s in segs], dtype=float)
        return cls(received, times, ctrl, [s.get("corridor") for s in segs])

    @property
    def t0(self) -> float:
        return float(self.times[0])

    @property
    def t_end(self) -> float:
        return float(self.times[-1])

    @property
    def is_fresh_hold(self) -> bool:
        """The hold the companion streams when it takes control (a new time base, t = 0)."""
        return (len(self.ctrl) == 1 and self.t0 == 0.0
                and bool(np.all(np.abs(self.ctrl - self.ctrl[0, 0]) == 0.0)))

    def junctions(self) -> tuple[np.ndarray, np.ndarray]:
        """(times, positions) of every segment end point."""
        pos = np.vstack([self.ctrl[:, 0, :], self.ctrl[-1:, -1, :]])
        return self.times.copy(), pos

    def evaluate(self, ts: np.ndarray) -> np.ndarray:
        ts = np.clip(np.atleast_1d(np.asarray(ts, dtype=float)), self.t0, self.t_end)
        j = np.clip(np.searchsorted(self.times, ts, side="right") - 1, 0, len(self.ctrl) - 1)
        span = self.times[j + 1] - self.times[j]
        u = np.where(span > 0, (ts - self.times[j]) / np.where(span > 0, span, 1.0), 0.0)
        k = np.arange(DEGREE + 1)
        basis = _BINOM * u[:, None] ** k * (1.0 - u[:, None]) ** (DEGREE - k)
        return np.einsum("nk,nkd->nd", basis, self.ctrl[j])

    def bound_violations(self) -> list[str]:
        """Convex-hull certificate, rechecked: the control points of the hodographs' CERT_PIECES
        pieces within the bounds and control points inside each segment's corridor (1e-6 slack)."""
        out: list[str] = []
        for s in range(len(self.ctrl)):
            span = self.times[s + 1] - self.times[s]
            p = self.ctrl[s]
            if span <= 0:
                out.append(f"segment {s}: non-positive duration {span}")
                continue
            vel = DEGREE / span * np.diff(p, axis=0)
            acc = _pieces((DEGREE - 1) / span * np.diff(vel, axis=0))
            vel = _pieces(vel)
            if np.max(np.abs(vel)) > VELOCITY_BOUND + 1e-6:
                out.append(f"segment {s} [{self.times[s]:.3f}, {self.times[s + 1]:.3f}]: "
                           f"velocity control point {np.max(np.abs(vel)):.4f} > {VELOCITY_BOUND}")
            if np.max(np.abs(acc)) > ACCELERATION_BOUND + 1e-6:
                out.append(f"segment {s} [{self.times[s]:.3f}, {self.times[s + 1]:.3f}]: "
                           f"acceleration control point {np.max(np.abs(acc)):.4f} > {ACCELERATION_BOUND}")
            c = self.corridors[s]
            if c is not None:
                a, b = np.asarray(c["A"], dtype=float), np.asarray(c["b"], dtype=float)
                excess = float(np.max(p @ a.T - b))
                if excess > 1e-6:
                    out.append(f"segment {s}: a control point is {excess:.2e} m outside its corridor")
        return out


def match_waypoints(plan: Plan, waypoints: list[list[float]], tol: float = WAYPOINT_TOL) -> list[float | None]:
    """For each waypoint, the junction time at which the plan passes it (in order), or None.

    Matched from the end backwards, each waypoint at the latest junction before the next
    one's, so a plan that passes the later waypoints in order and lacks a prefix (already
    flown and trimmed) shows as [None, ..., None, t_k, ..., t_m].
    """
    jt, jp = plan.junctions()
    out: list[float | None] = [None] * len(waypoints)
    limit = len(jt)
    for i in range(len(waypoints) - 1, -1, -1):
        d = np.linalg.norm(jp[:limit] - np.asarray(waypoints[i], dtype=float), axis=1)
        hits = np.nonzero(d <= tol)[0]
        if len(hits):
            limit = int(hits[-1])
            out[i] = float(jt[limit])
    return out


def nearest_distance(plan: Plan, point: list[float] | np.ndarray, t_from: float | None = None) -> float:
    ts = np.linspace(plan.t0 if t_from is None else max(t_from, plan.t0), plan.t_end, 4000)
    return float(np.min(np.linalg.norm(plan.evaluate(ts) - np.asarray(point, dtype=float), axis=1)))


def inside_box(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, inflate: float) -> np.ndarray:
    """Inside the box grown by `inflate` (Minkowski sum with a ball, as the planner inflates
    half-spaces: each face moved out by the radius; corners kept square)."""
    p = np.atleast_2d(points)
    return np.all((p >= lo - inflate) & (p <= hi + inflate), axis=1)


class SeqRig(Rig):
    """The e2e Rig plus helpers that do not raise (the caller decides what a timeout means)."""

    def plans(self, since: int = 0) -> list[Plan]:
        with self.lock:
            raw = list(self.trajectories[since:])
        return [Plan.from_message(r, obj) for r, obj in raw]

    def n_plans(self) -> int:
        with self.lock:
            return len(self.trajectories)

    def status(self) -> dict[str, Any]:
        with self.lock:
            return dict(self.statuses[-1]) if self.statuses else {}

    def n_statuses(self) -> int:
        with self.lock:
            return len(self.statuses)

    def find_event(self, pred: Callable[[dict[str, Any]], bool], timeout: float, since: int = 0,
                   stop_on_error: bool = True) -> dict[str, Any] | None:
        """The first event since `since` that `pred` accepts; an `error` event (an internal
        error in a handler: nothing more will come) ends the wait and is returned."""
        deadline = time.monotonic() + timeout
        while True:
            with self.lock:
                for e in self.events[since:]:
                    if pred(e) or (stop_on_error and e["type"] == "error"):
                        return e
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.02)

    def until(self, pred: Callable[[], bool], timeout: float, period: float = 0.05) -> bool:
        deadline = time.monotonic() + timeout
        while True:
            if pred():
                return True
            if time.monotonic() >= deadline:
                return False
            time.sleep(period)

    def mock(self) -> dict[str, Any]:
        assert self.control is not None
        return self.control.state()

    def wait_new_plan(self, n_before: int, timeout: float = 1.5) -> bool:
        return self.until(lambda: self.n_plans() > n_before, timeout, 0.02)

    def wait_fresh_status(self, timeout: float = 1.5) -> dict[str, Any]:
        n = self.n_statuses()
        self.until(lambda: self.n_statuses() > n, timeout, 0.02)
        return self.status()

    def read_log(self) -> list[dict[str, Any]]:
        time.sleep(0.6)  # the mock flushes every 0.5 s
        out = []
        with open(self.log_path, encoding="utf-8") as fh:
            for line in fh:
                with contextlib.suppress(json.JSONDecodeError):
                    out.append(json.loads(line))
        return out

    def restart_companion(self) -> None:
        """Kill and restart the companion process only; the mock keeps flying. The Zenoh
        client session is reopened (its endpoint is the companion's listener)."""
        if self.session is not None:
            with contextlib.suppress(Exception):
                self.session.close()
            self.session = None
        comp = self.procs[1]
        comp.kill()
        comp.wait(10)
        cfg = self.tmp / f"{self.autopilot}.toml"
        env = {**os.environ, "PYTHONUNBUFFERED": "1"}
        err = open(self.tmp / f"{self.autopilot}-companion-2.err", "wb")  # noqa: SIM115
        self.procs[1] = subprocess.Popen([sys.executable, "-m", "companion", "run", "--config", str(cfg)],
                                         cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=err)
        import zenoh

        zc = zenoh.Config()
        zc.insert_json5("mode", '"client"')
        zc.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{self.zport}"]))
        zc.insert_json5("scouting/multicast/enabled", "false")
        deadline = time.monotonic() + 30
        while True:
            try:
                self.session = zenoh.open(zc)
                break
            except zenoh.ZError:
                if time.monotonic() > deadline or self.procs[1].poll() is not None:
                    raise RuntimeError(f"companion did not come back; see {self.tmp}") from None
                time.sleep(0.2)
        with self.lock:
            self.statuses.clear()
        self.session.declare_subscriber(self.key("events"), self._on("events"))
        self.session.declare_subscriber(self.key("status"), self._on("status"))
        self.session.declare_subscriber(self.key("trajectory"), self._on("trajectory"))
        self.wait_status(lambda s: s.get("autopilot") == self.autopilot and s.get("link"), 30,
                         "autopilot link after the restart")


# The vehicle at a mission's end: within SETTLE_TOL of the last waypoint and slower than
# SETTLE_SPEED, within SETTLE_TIME of `mission_complete` (the plan's end time). A fixed 0.5 s
# sufficed for sitl_mock's calibrated response (ArduCopter's: it settles to ~0.01 m by then);
# PX4's default (`px4_sih`: PX4's default gains MPC_XY_P 0.95 / MPC_XY_VEL_P_ACC 1.8, the
# measured 0.3 s delay) carries a vehicle 0.1-0.4 m past a rest-to-rest plan's end, whatever the
# lead (0.30-0.45 s), 0.5 s after it, and brings it back over ~2 s.
SETTLE_TOL = 0.15  # m
SETTLE_SPEED = 0.2  # m/s ([safety] rest_speed)
SETTLE_TIME = 3.0  # s


def settled_miss(rig: SeqRig, goal: list[float] | np.ndarray, timeout: float = SETTLE_TIME) -> float:
    """The vehicle's distance from `goal` once it has settled there (SETTLE_TOL, SETTLE_SPEED), or
    the distance it was at when `timeout` ran out."""
    goal = np.asarray(goal, dtype=float)
    deadline = time.monotonic() + timeout
    while True:
        s = rig.mock()
        miss = float(np.linalg.norm(np.asarray(s["position"]) - goal))
        if (miss <= SETTLE_TOL and float(np.linalg.norm(s["velocity"])) <= SETTLE_SPEED) or time.monotonic() >= deadline:
            return miss
        time.sleep(0.05)


def event_brief(e: dict[str, Any]) -> str:
    return f"{e.get('type')}[{e.get('state')}]: {e.get('message')}"


def fmt(v: Any) -> str:
    return json.dumps(v) if not isinstance(v, float) else f"{v:.4f}" if math.isfinite(v) else str(v)
