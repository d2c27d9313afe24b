"""The recording's 3D channels (Foxglove's own message types, local_enu): the vehicle's pose and
its frame transform, the planned and the flown path, the obstacles and the corridors ahead, and
the bounds each plan was given (JSON, `/viz/bounds`). `Viz` turns what the recorder is shown into
their messages, on the writer thread; the channels' names and schemas are companion.channels'.
"""

from __future__ import annotations

import collections
import math
from typing import Any

import numpy as np

from companion.channels import bounds_fields, dumps
from companion.wire.frames import swap_points

FLOWN_KEEP = 1500  # points of the flown path kept (at FLOWN_EVERY s apart: 10 min)
FLOWN_EVERY = 0.4  # s
FLOWN_PUBLISH = 1.0  # s between /viz/flown_path messages
PLANNED_POINTS = 400  # poses sampled along the planned path


# -- Foxglove 3D --------------------------------------------------------------------------------


def _quat_enu(roll: float, pitch: float, yaw: float) -> tuple[float, float, float, float]:
    """A FRD body's attitude in NED (roll, pitch, yaw) as the FLU body's quaternion in ENU."""
    r, p, y = roll, -pitch, math.pi / 2 - yaw
    cr, sr = math.cos(r / 2), math.sin(r / 2)
    cp, sp = math.cos(p / 2), math.sin(p / 2)
    cy, sy = math.cos(y / 2), math.sin(y / 2)
    return (sr * cp * cy - cr * sp * sy, cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy, cr * cp * cy + sr * sp * sy)


class Viz:
    """Foxglove 3D messages from what the recorder sees (in the writer thread only)."""

    def __init__(self) -> None:
        self.attitude = (0.0, 0.0, 0.0)
        self.flown: collections.deque[tuple[float, float, float]] = collections.deque(maxlen=FLOWN_KEEP)
        self._last_flown = -math.inf
        self._last_flown_pub = -math.inf
        self.offset = 0.0  # monotonic to unix (set by the recorder)

    def _ts(self, t: float) -> Any:
        from foxglove.messages import Timestamp

        t += self.offset
        sec = math.floor(t)
        return Timestamp(int(sec), int((t - sec) * 1e9))

    def on_mavlink(self, msg: Any, t: float) -> list[tuple[str, bytes]]:
        kind = msg.get_type()
        if kind == "ATTITUDE":
            self.attitude = (msg.roll, msg.pitch, msg.yaw)
            return []
        if kind != "LOCAL_POSITION_NED":
            return []
        from foxglove.messages import (
            FrameTransform,
            Pose,
            PoseInFrame,
            PosesInFrame,
            Quaternion,
            Vector3,
        )

        e = swap_points(np.array([msg.x, msg.y, msg.z], dtype=float))
        q = Quaternion(**dict(zip("xyzw", _quat_enu(*self.attitude), strict=True)))
        pos = Vector3(x=float(e[0]), y=float(e[1]), z=float(e[2]))
        ts = self._ts(t)
        out = [
            ("/viz/vehicle", PoseInFrame(timestamp=ts, frame_id="local_enu", pose=Pose(position=pos, orientation=q)).encode()),
            ("/viz/tf", FrameTransform(timestamp=ts, parent_frame_id="local_enu", child_frame_id="vehicle",
                                       translation=pos, rotation=q).encode()),
        ]
        if t - self._last_flown >= FLOWN_EVERY:
            self._last_flown = t
            self.flown.append((float(e[0]), float(e[1]), float(e[2])))
        if t - self._last_flown_pub >= FLOWN_PUBLISH and self.flown:
            self._last_flown_pub = t
            ident = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
            poses = [Pose(position=Vector3(x=x, y=y, z=z), orientation=ident) for x, y, z in self.flown]
            out.append(("/viz/flown_path", PosesInFrame(timestamp=ts, frame_id="local_enu", poses=poses).encode()))
        return out

    def on_flown(self, traj: Any, t_base: float | None, t: float) -> list[tuple[str, bytes]]:
        """The plan flown from now on: its path, and the corridors of the segments ahead."""
        from foxglove.messages import Pose, PosesInFrame, Quaternion, Vector3

        ts = self._ts(t)
        now = -math.inf if t_base is None else t - t_base
        times = np.linspace(max(traj.t0, min(now, traj.t_end)), traj.t_end, PLANNED_POINTS)
        pts = swap_points(np.asarray(traj.evaluate(times), dtype=float))
        ident = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
        poses = [Pose(position=Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])), orientation=ident) for p in pts]
        out = [("/viz/planned_path", PosesInFrame(timestamp=ts, frame_id="local_enu", poses=poses).encode())]
        corridors = traj.corridors or ()
        ahead = [c for s, c in enumerate(corridors) if c is not None and traj.times[s + 1] >= now]
        out.append(("/viz/corridors", self._scene(ts, "corridor", ahead[:64], (0.2, 0.6, 1.0, 0.15))))
        return out

    def on_plan(self, args: tuple[Any, ...], result: Any, t: float) -> list[tuple[str, bytes]]:
        """The obstacles a plan was made against, and the bounds it used."""
        from companion.obstacles import Known

        out: list[tuple[str, bytes]] = []
        known = next((a for a in args if isinstance(a, Known)), None)
        if known is not None:
            out.append(("/viz/obstacles", self._scene(self._ts(t), "obstacle", list(known.polytopes)[:256],
                                                  (1.0, 0.3, 0.2, 0.5))))
        route = getattr(result, "route", None)
        # the bounds the planner was given (the mission's, less [planner] reserve when it applies)
        bounds = getattr(getattr(route, "problem", None), "bounds", None)
        if bounds is not None:
            out.append(("/viz/bounds", dumps({"t": t, **bounds_fields(bounds)})))
        return out

    @staticmethod
    def _scene(ts: Any, kind: str, polytopes: list[Any], rgba: tuple[float, float, float, float]) -> bytes:
        """One SceneUpdate replacing every entity of `kind`: a triangle mesh per polytope."""
        from foxglove.messages import (
            Color,
            Point3,
            SceneEntity,
            SceneEntityDeletion,
            SceneEntityDeletionType,
            SceneUpdate,
            TriangleListPrimitive,
        )
        from scipy.spatial import ConvexHull

        from planner_core import polytope_vertices

        color = Color(r=rgba[0], g=rgba[1], b=rgba[2], a=rgba[3])
        entities = []
        for i, poly in enumerate(polytopes):
            try:
                v = swap_points(polytope_vertices(poly))
                tri = v[ConvexHull(v).simplices].reshape(-1, 3)
            except Exception:  # unbounded or flat: nothing to draw
                continue
            entities.append(SceneEntity(
                timestamp=ts, frame_id="local_enu", id=f"{kind}/{i}", frame_locked=True,
                triangles=[TriangleListPrimitive(points=[Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]))
                                                         for p in tri], color=color)]))
        # each message replaces the whole scene of its channel (/viz/obstacles, /viz/corridors)
        deletions = [SceneEntityDeletion(timestamp=ts, type=SceneEntityDeletionType.All)]
        return bytes(SceneUpdate(deletions=deletions, entities=entities).encode())
