"""What the recorder tests share: a configuration, real MAVLink messages, a real plan."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from pymavlink.dialects.v20 import common as mavlink2

from companion.config import Config, LimitsConfig, LiveConfig, PlannerConfig, RecordingConfig
from companion.mission import start_mission
from companion.obstacles import Known
from companion.route import Outcome
from companion.wire.messages import MissionSpec, read
from planner_core import rest_jet


def schema_checked(path: Path, topic: str, schema_name: str) -> list[dict[str, Any]]:
    """The records on `topic`, each valid against the JSON schema the file carries for it, which
    must be `schema_name` (a viewer reads the channel by it)."""
    import jsonschema
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        found = list(make_reader(fh).iter_messages(topics=[topic]))
    assert found, f"no record on {topic}"
    schema, channel, _m = found[0]
    assert schema is not None and (schema.name, channel.message_encoding) == (schema_name, "json")
    recs = [json.loads(m.data) for _s, _c, m in found]
    for r in recs:
        jsonschema.validate(r, json.loads(schema.data))
    return recs


def config(path: Path | str = "", queue: int = 4096, live: str = "", **rec: Any) -> Config:
    # a cold process checks its first obstacle slowly (imports): no decode deadline here
    # the mission's box was placed for the vehicle radius alone (planning tests set no tracking
    # allowance, as tests/companion/test_route.py does)
    return Config(recording=RecordingConfig(path=str(path), queue=queue, **rec), live=LiveConfig(foxglove=live),
                  limits=LimitsConfig(decode_deadline=60.0), planner=PlannerConfig(tracking_allowance=0.0))


class Wire:
    """A real pymavlink encoder whose every send goes to `on_sent` (as MavlinkLink's does), and
    a decoder for what it wrote: messages as the link receives them."""

    def __init__(self, on_sent: Any = None) -> None:
        self.buf = bytearray()
        self.tx = mavlink2.MAVLink(self, srcSystem=1, srcComponent=191)
        if on_sent is not None:
            self.tx.set_send_callback(on_sent)
        self.rx = mavlink2.MAVLink(None)

    def write(self, data: bytes) -> None:  # the "file" pymavlink writes to
        self.buf += data

    def setpoint(self, k: int) -> None:
        self.tx.set_position_target_local_ned_send(k, 1, 1, 1, 2048, 0.01 * k, 0.0, -1.0, 0.5, 0.0, 0.0,
                                                   0.0, 0.0, 0.0, 0.0, 0.0)

    def received(self, msg: Any) -> Any:
        """`msg` as the other end decodes it (header, source ids)."""
        return self.rx.parse_buffer(msg.pack(self.tx))[0]


MISSION = {"id": "rec", "frame": "ned", "waypoints": [[0.0, 0.0, -1.0], [4.0, 0.0, -1.0], [4.0, 4.0, -1.5]],
           "obstacles": [{"id": "box", "vertices": [[x, y, z] for x in (1.5, 2.5) for y in (-0.5, 0.5) for z in (-3.0, 0.0)]}]}


def mission(cfg: Config, **changes: Any) -> MissionSpec:
    spec = read("mission", json.dumps({**MISSION, **changes}).encode(), cfg, None)
    assert isinstance(spec, MissionSpec), spec
    return replace(spec, raw={})


def plan_call(cfg: Config, **changes: Any) -> tuple[Any, tuple[Any, ...], Outcome]:
    """A real planner call as the service makes it: (function, arguments, result)."""
    args = (mission(cfg, **changes), rest_jet(np.array([-0.5, 0.0, -1.0])), 0.0, Known(), cfg)
    out = start_mission(*args)
    assert out.ok, out.message
    return start_mission, args, out


# -- the tracking error's stand-ins (tests/companion/test_replay_tracking.py, benchmarks/recorder.py) --


class ScriptedControl:
    """companion.control.Control as companion.tracking.Tracking reads it: the error of each sample
    is `error` (scripted), the setpoint a fixed point, no plan streamed for the lag estimate."""

    def __init__(self) -> None:
        self.error = 0.0
        self.streaming, self.active, self.t_base = False, None, None

    def tracking_error(self, _position: Any, _at: float) -> float:
        return self.error

    def reference(self, _at: float) -> Any:
        return np.array([1.0, 2.0, -1.5])


class BrakingNavigator:
    """companion.navigator.Navigator.hold as the brakes carry it out: a stop planned, Braking
    with the reason, then stopped and holding."""

    def __init__(self, sup: Any) -> None:
        self.sup = sup

    async def hold(self, reason: str, _arrived: float | None) -> None:
        import asyncio

        from companion.supervisor import Braking, StoppedAfterBraking

        await asyncio.sleep(0.01)
        self.sup.handle(Braking(reason))
        await asyncio.sleep(0.01)
        self.sup.handle(StoppedAfterBraking())


class TrackingLink:
    def __init__(self) -> None:
        from companion.wire.vehicle import VehicleState

        self.state = VehicleState(autopilot="px4")
