"""What goes out on Zenoh: status, telemetry, event bodies and trajectory JSON."""

from __future__ import annotations

import json
import math
import time
from typing import Any

import numpy as np

from planner_core import Trajectory, trajectory_to_dict


def encode(obj: Any) -> bytes:
    return json.dumps(obj, separators=(",", ":"), allow_nan=False).encode()


def num(x: float | None, nd: int = 4) -> float | None:
    """A rounded float for JSON, None for a missing or non-finite value."""
    return None if x is None or not math.isfinite(x) else round(float(x), nd)


def vec(v: Any) -> list[float] | None:
    a = np.asarray(v, dtype=float)
    return None if not np.all(np.isfinite(a)) else [round(float(x), 4) for x in a]


def ms(seconds: float | None, nd: int = 2) -> float | None:
    return num(None if seconds is None else seconds * 1000, nd)


def event_body(kind: str, state: str, message: str, **extra: Any) -> dict[str, Any]:
    return {"type": kind, "time": round(time.time(), 3), "state": state, "message": message, **extra}


def encode_trajectory(traj: Trajectory, fleet: dict[str, Any] | None = None) -> bytes:
    """Trajectory JSON, one segment per json.dumps call so other threads get the GIL between.
    `fleet`: the fleet object (companion.deconfliction; only with [fleet] separation)."""
    head = trajectory_to_dict(Trajectory(traj.times[:2], traj.control_points[:1], None, traj.stats), "ned")
    if fleet is not None:
        head["fleet"] = fleet
    head["segments"] = []
    parts = []
    corridors = traj.corridors or (None,) * traj.n_segments
    for s in range(traj.n_segments):
        c = corridors[s]
        parts.append(json.dumps({
            "t0": float(traj.times[s]), "t1": float(traj.times[s + 1]),
            "control_points": traj.control_points[s].tolist(),
            "corridor": None if c is None else {"A": c.A.tolist(), "b": c.b.tolist()},
        }, separators=(",", ":")))
    text = json.dumps(head, separators=(",", ":"), default=str)
    return text.replace('"segments":[]', '"segments":[' + ",".join(parts) + "]", 1).encode()


def telemetry(position: Any, velocity: Any, attitude: Any, armed: bool, mode: str) -> dict[str, Any]:
    return {
        "time": round(time.time(), 3),
        "frame": "ned",
        "position": vec(position),
        "velocity": vec(velocity),
        "attitude": {"roll": num(attitude[0]), "pitch": num(attitude[1]), "yaw": num(attitude[2])},
        "armed": armed,
        "mode": mode,
    }
