"""The fleet frame in the companion (issue 24.2): `[fleet] origin`, where the autopilot's local
frame sits in it (companion.fleet.FleetFrame, from GPS_GLOBAL_ORIGIN, HOME_POSITION or a
configured offset), and messages that say `"origin": "fleet"` (companion.wire.messages.read)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from companion.config import Config, FleetConfig, config_from_dict
from companion.fleet import FleetFrame
from companion.geodesy import Placement, lla_to_ned, ned_to_lla
from companion.wire.messages import Change, MessageError, MissionSpec, ObstacleUpdate, read

FLEET = (47.397742, 8.545594, 488.0)
# the vehicle's EKF origin: 30 m north, 40 m west of the fleet origin, 1.6 m above it
LOCAL = ned_to_lla([30.0, -40.0, -1.6], FLEET)


def _cfg(**fleet: object) -> Config:
    return config_from_dict({"fleet": {"origin": list(FLEET), **fleet},
                             "geofence": {"min": [-100, -100, -50], "max": [100, 100, 5], "origin": "local"}})


def test_no_fleet_by_default() -> None:
    frame = FleetFrame(FleetConfig())
    assert not frame.enabled and frame.for_messages() is None and frame.status() is None
    assert frame.update(LOCAL, None, None) is None


def test_placed_from_gps_global_origin_then_moved() -> None:
    frame = FleetFrame(_cfg().fleet)
    assert isinstance(frame.for_messages(), str)  # not yet: the reason
    assert frame.status() == {**frame.status(), "placed": False, "frame": "unknown"}  # type: ignore[dict-item]
    said = frame.update(LOCAL, None, None)
    assert said is not None and "placed from gps_global_origin" in said
    pl = frame.for_messages()
    assert isinstance(pl, Placement) and np.allclose(pl.offset, [30.0, -40.0, -1.6], atol=1e-6)
    st = frame.status()
    assert st is not None and st["placed"] and st["source"] == "gps_global_origin"
    assert st["offset_ned"] == [30.0, -40.0, -1.6] and st["clock_tolerance"] == 0.05
    # the same origin again (re-sent, rounded): no event
    assert frame.update((LOCAL[0] + 1e-8, LOCAL[1], LOCAL[2] + 0.001), None, None) is None
    # an EKF origin reset: said, with how far it moved
    moved = frame.update(ned_to_lla([35.0, -40.0, -1.6], FLEET), None, None)
    assert moved is not None and "moved by 5.00 m" in moved


def test_placed_from_home_position() -> None:
    """HOME_POSITION: home geodetic and in the local frame give the local origin."""
    frame = FleetFrame(_cfg().fleet)
    home_local = np.array([-0.24, -0.49, 1.48])
    home_lla = ned_to_lla(home_local, LOCAL)
    said = frame.update(None, home_lla, home_local)
    assert said is not None and "home_position" in said
    pl = frame.for_messages()
    assert isinstance(pl, Placement) and np.allclose(pl.offset, [30.0, -40.0, -1.6], atol=1e-6)
    # GPS_GLOBAL_ORIGIN, when it comes, is preferred (a different source: said)
    assert frame.update(LOCAL, home_lla, home_local) is not None
    assert frame.status()["source"] == "gps_global_origin"  # type: ignore[index]


def test_configured_offset_for_a_vehicle_without_gps() -> None:
    frame = FleetFrame(_cfg(offset_ned=[5.0, 6.0, 0.0]).fleet)
    pl = frame.for_messages()
    assert isinstance(pl, Placement) and pl.source == "offset_ned" and np.allclose(pl.offset, [5, 6, 0])
    assert frame.update(LOCAL, None, None) is None  # the configuration wins
    assert frame.status()["source"] == "offset_ned"  # type: ignore[index]


def test_another_site_is_not_placed() -> None:
    frame = FleetFrame(_cfg().fleet)
    said = frame.update((48.9, 2.35, 35.0), None, None)  # Paris, ~480 km away
    assert said is not None and "cannot place" in said and "km from [fleet] origin" in said
    assert isinstance(frame.for_messages(), str)
    assert frame.status()["placed"] is False  # type: ignore[index]


def _read(kind: str, body: dict[str, object], cfg: Config, fleet: Placement | str | None) -> object:
    return read(kind, json.dumps(body).encode(), cfg, None, fleet=fleet)


def test_a_fleet_mission_is_flown_in_the_local_frame() -> None:
    cfg = _cfg()
    frame = FleetFrame(cfg.fleet)
    frame.update(LOCAL, None, None)
    pl = frame.for_messages()
    wps = [[30.0, -40.0, -3.0], [34.0, -40.0, -3.0], [34.0, -36.0, -3.0]]  # fleet NED
    box = {"A": [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
           "b": [33.0, -32.0, -37.0, 39.0, 0.0, 4.0]}  # x in [32, 33], y in [-39, -37] (fleet)
    msg = _read("mission", {"id": "m", "origin": "fleet", "waypoints": wps, "obstacles": [box]}, cfg, pl)
    assert isinstance(msg, MissionSpec), msg
    # fleet minus where the local origin is in the fleet frame: [0, 0, -1.4], [4, 0, -1.4], [4, 4, -1.4]
    # (to 0.1 mm: the two tangent planes, 50 m apart, are turned by ~1e-5 rad)
    assert np.allclose(msg.waypoints, np.asarray(wps) - [30.0, -40.0, -1.6], atol=1e-4)
    poly = msg.obstacles[0][1]
    centre_fleet = np.array([32.5, -38.0, -2.0])
    local_centre = centre_fleet - [30.0, -40.0, -1.6]
    assert np.all(poly.A @ local_centre <= poly.b + 1e-9)
    assert not np.all(poly.A @ centre_fleet <= poly.b)  # the fleet coordinates are not local ones
    # in ENU about the fleet origin too
    enu = [[w[1], w[0], -w[2]] for w in wps]
    msg_enu = _read("mission", {"id": "m", "frame": "enu", "origin": "fleet", "waypoints": enu}, cfg, pl)
    assert isinstance(msg_enu, MissionSpec) and np.allclose(msg_enu.waypoints, msg.waypoints)


def test_fleet_obstacles_and_changes() -> None:
    cfg = _cfg()
    pl = Placement(np.array([30.0, -40.0, -1.6]))
    obs = _read("obstacles", {"origin": "fleet", "add": [
        {"id": "post", "vertices": [[31, -39, 0], [32, -39, 0], [31, -38, 0], [31, -39, -3]]}]}, cfg, pl)
    assert isinstance(obs, ObstacleUpdate), obs
    inside_local = np.array([31.2, -38.8, -0.5]) - pl.offset
    poly = obs.add[0][1]
    assert np.all(poly.A @ inside_local <= poly.b + 1e-9)
    ch = _read("change", {"origin": "fleet", "move_waypoint": {"index": 1, "position": [31.0, -39.0, -3.0]}},
               cfg, pl)
    assert isinstance(ch, Change), ch
    assert np.allclose(ch.body.position, [1.0, 1.0, -1.4])  # type: ignore[union-attr]


@pytest.mark.parametrize(("fleet", "words"), [
    (None, "needs [fleet] origin"),
    ("waiting for the autopilot's GPS_GLOBAL_ORIGIN", "cannot be placed yet: waiting for the autopilot"),
])
def test_fleet_messages_refused_while_the_frame_is_unknown(fleet: str | None, words: str) -> None:
    cfg = _cfg()
    msg = _read("mission", {"id": "m", "origin": "fleet", "waypoints": [[0, 0, -2], [1, 0, -2]]}, cfg, fleet)
    assert isinstance(msg, MessageError) and msg.field == "origin" and words in msg.reason, msg


def test_local_and_home_messages_unchanged_with_a_fleet() -> None:
    cfg = _cfg()
    pl = Placement(np.array([30.0, -40.0, -1.6]))
    wps = [[0.0, 0.0, -2.0], [1.0, 0.0, -2.0]]
    msg = _read("mission", {"id": "m", "waypoints": wps}, cfg, pl)
    assert isinstance(msg, MissionSpec) and np.allclose(msg.waypoints, wps)


def test_fleet_config() -> None:
    cfg = _cfg(offset_ned=[1, 2, 3], clock_tolerance=0.2)
    assert cfg.fleet.origin == FLEET and cfg.fleet.offset_ned == (1.0, 2.0, 3.0) and cfg.fleet.clock_tolerance == 0.2
    assert Config().fleet.origin == ()
    assert np.allclose(lla_to_ned(LOCAL, FLEET), [30.0, -40.0, -1.6], atol=1e-6)


def test_fleet_tool_says_when_a_vehicles_clock_is_off() -> None:
    """`python -m companion fleet`: the vehicle's status time against this computer's clock,
    said when it is off by more than the vehicle's [fleet] clock_tolerance beyond the round trip."""
    from companion.cli_fleet import clock_warning

    status = {"fleet": {"clock_tolerance": 0.05}}
    ok = {"vehicle": "a", "status": status, "clock_offset_ms": 60.0, "clock_uncertainty_ms": 15.0}
    off = {"vehicle": "b", "status": status, "clock_offset_ms": -120.0, "clock_uncertainty_ms": 5.0}
    assert clock_warning(ok) is None  # 60 - 15 <= 50: may be within
    said = clock_warning(off)
    assert said is not None and "-120 ms" in said and "clock_tolerance (50 ms)" in said
    assert clock_warning({"vehicle": "c", "status": {"fleet": None}, "clock_offset_ms": 900.0,
                          "clock_uncertainty_ms": 1.0}) is None  # no fleet: nothing assumed
