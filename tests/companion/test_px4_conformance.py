"""What a real PX4 1.15 does that the companion must follow (issue 15), below the service:
home-relative messages, the takeoff altitude above the ground, PX4's mode reports (armed
state first) and the setpoint thread's stall latch."""

from __future__ import annotations

import json
import threading
import time
from typing import Any

import numpy as np
import pytest

from companion.autopilot import AutopilotWatch
from companion.commands import Commands
from companion.config import Config
from companion.flight import FlightState, State
from companion.report import Reporter
from companion.setpoints import Feed, Liveness, SetpointSender, Tick, YawPolicy
from companion.supervisor import GroundLearnt, HeightReport, LandRequested, Supervisor
from companion.wire.messages import Command, MessageError, MissionSpec, ObstacleUpdate, read
from companion.wire.vehicle import VehicleState, decode_mode
from planner_core import hold

S = State
CFG = Config()
HOME = np.array([0.5, -1.0, 1.6])  # NED: PX4's ground sits 1.6 m below its local origin


def mission(**extra: Any) -> bytes:
    return json.dumps({"id": "m", "waypoints": [[1.0, 0.0, -2.0], [3.0, 0.0, -2.0]], **extra}).encode()


def test_home_relative_mission_and_obstacles_are_shifted_into_the_local_frame() -> None:
    local = read("mission", mission(), CFG, HOME)
    assert isinstance(local, MissionSpec)
    np.testing.assert_allclose(local.waypoints, [[1.0, 0.0, -2.0], [3.0, 0.0, -2.0]])
    box = {"id": "b", "A": [[1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0], [0, 0, 1], [0, 0, -1]],
           "b": [2.5, -1.5, 1, 1, 3, 0]}
    rel = read("mission", mission(origin="home", obstacles=[box]), CFG, HOME)
    assert isinstance(rel, MissionSpec)
    np.testing.assert_allclose(rel.waypoints, local.waypoints + HOME)
    # the same solid, moved by home: a point inside it relative to home is inside it in local
    poly = rel.obstacles[0][1]
    inside = np.array([2.0, 0.0, 1.0]) + HOME
    assert np.all(poly.A @ inside <= poly.b) and not np.all(poly.A @ np.array([2.0, 0.0, 1.0]) <= poly.b)
    # ENU in, home-relative: the swap first (z up), then the shift
    enu = read("mission", json.dumps({"id": "e", "origin": "home", "frame": "enu", "waypoints": [[1, 0, 2]]}).encode(),
               CFG, HOME)
    assert isinstance(enu, MissionSpec)
    np.testing.assert_allclose(enu.waypoints[0], np.array([0.0, 1.0, -2.0]) + HOME)
    obs = read("obstacles", json.dumps({"origin": "home", "add": [{"id": "v", "vertices": [
        [x, y, z] for x in (0, 1) for y in (0, 1) for z in (-1, 0)]}]}).encode(), CFG, HOME)
    assert isinstance(obs, ObstacleUpdate)
    change = read("change", json.dumps({"origin": "home", "move_waypoint": {"index": 1, "position": [0, 0, -2]}})
                  .encode(), CFG, HOME)
    np.testing.assert_allclose(change.body.position, np.array([0.0, 0.0, -2.0]) + HOME)  # type: ignore[union-attr]


def test_a_home_relative_message_is_refused_while_home_is_unknown() -> None:
    for kind, payload in (("mission", mission(origin="home")),
                          ("obstacles", b'{"origin": "home", "clear": true}'),
                          ("change", b'{"origin": "home", "remove_waypoint": {"index": 1}}')):
        err = read(kind, payload, CFG, None)
        assert isinstance(err, MessageError), kind
        assert err.field == "origin" and "HOME_POSITION" in err.reason
    # the local frame needs no home
    assert isinstance(read("mission", mission(origin="local"), CFG, None), MissionSpec)


def test_a_refusal_of_a_shifted_position_says_the_frame_it_names() -> None:
    err = read("mission", json.dumps({"id": "m", "origin": "home", "waypoints": [[0, 0, -1.0]]}).encode(),
               config_with_fence(), HOME)
    assert isinstance(err, MessageError)
    assert "local frame" in err.reason and "[0.5, -1, 1.6]" in err.reason, err.reason


def config_with_fence() -> Config:
    from companion.config import config_from_dict
    return config_from_dict({"geofence": {"min": [-10, -10, -10], "max": [10, 10, 0.0], "origin": "local"}})


def test_the_geofence_follows_home_so_its_floor_follows_the_ground() -> None:
    low = json.dumps({"id": "low", "waypoints": [[0.0, 0.0, 1.0]]}).encode()  # 0.6 m above PX4's ground
    assert isinstance(read("mission", low, CFG, HOME), MissionSpec)  # [geofence] origin = "home"
    local = read("mission", low, config_with_fence(), HOME)
    assert isinstance(local, MessageError) and "geofence" in local.reason
    spec = read("mission", mission(), CFG, HOME)
    assert isinstance(spec, MissionSpec)
    np.testing.assert_allclose(spec.map_hi, np.asarray(CFG.geofence.max) + HOME)


def test_takeoff_takes_origin_and_only_takeoff_does() -> None:
    assert read("command", b'{"command": "takeoff", "altitude": 2, "origin": "home"}', CFG) == \
        Command("takeoff", 2.0, "home")
    assert read("command", b'{"command": "takeoff"}', CFG) == Command("takeoff", None, "ground")
    err = read("command", b'{"command": "land", "origin": "home"}', CFG)
    assert isinstance(err, MessageError) and err.field == "origin"


class _Link:
    def __init__(self, st: VehicleState) -> None:
        self.state = st

    def link_ok(self) -> bool:
        return time.monotonic() - self.state.last_heartbeat <= CFG.mavlink.link_timeout


def _commands(st: VehicleState, fl: Supervisor) -> Commands:
    return Commands(CFG, fl, None, _Link(st), None, Reporter(fl))  # type: ignore[arg-type]


def test_takeoff_altitude_is_above_the_ground_where_the_vehicle_stands() -> None:
    st, fl = VehicleState(autopilot="px4", home=HOME.copy()), Supervisor()
    st.position = np.array([0.5, -1.0, 1.6])  # on the ground, PX4's local z +1.6
    cmds = _commands(st, fl)
    target, above = cmds.takeoff_target(3.0)
    assert above == "the ground" and target[2] == pytest.approx(1.6 - 3.0)  # 3 m up, not z = -3
    # in the air (a second takeoff from READY): above the ground it stood on, not above here
    fl.handle(GroundLearnt(1.6))
    fl.handle(HeightReport(airborne=True))
    st.position = np.array([0.5, -1.0, -0.4])
    assert cmds.takeoff_target(3.0)[0][2] == pytest.approx(-1.4)
    # above home: home's z, wherever the vehicle is
    st.home = np.array([0.0, 0.0, 1.2])
    target, above = cmds.takeoff_target(2.0, "home")
    assert above == "home" and target[2] == pytest.approx(-0.8)


def _hb(st: VehicleState, mode_custom: int, armed: bool) -> None:
    st.autopilot, st.custom_mode, st.armed = "px4", mode_custom, armed
    st.base_mode = 1 | (128 if armed else 0)
    st.mode = decode_mode("px4", 2, st.base_mode, mode_custom)


PX4_LOITER = (4 << 16) | (3 << 24)  # AUTO.LOITER: main 4, sub 3
PX4_OFFBOARD = 6 << 16
PX4_LAND = (4 << 16) | (6 << 24)


def _watch(stalled: bool = False, state: State = S.IDLE, airborne: bool = False,
           ) -> tuple[AutopilotWatch, Supervisor, VehicleState, list[dict[str, Any]]]:
    fl, st = Supervisor(FlightState(state, airborne, seen_link=True)), VehicleState()
    events: list[dict[str, Any]] = []
    rep = Reporter(fl, lambda _k, body: events.append(body))
    w = AutopilotWatch(CFG, fl, _Link(st), rep, stalled=lambda: stalled)  # type: ignore[arg-type]
    return w, fl, st, events


def test_px4_modes_as_reported_boot_loiter_and_offboard_while_disarmed() -> None:
    w, fl, st, events = _watch()
    _hb(st, PX4_LOITER, armed=False)
    assert st.mode == "LOITER"  # PX4 >= 1.14 boots in AUTO.LOITER
    w.on_heartbeat()
    assert fl.state is S.IDLE and not events
    # a landing and auto-disarm in OFFBOARD: PX4 reports OFFBOARD while disarmed
    fl.handle(LandRequested())
    fl.handle(HeightReport(airborne=True))
    assert fl.state is S.LANDING and fl.airborne
    _hb(st, PX4_OFFBOARD, armed=False)
    w.on_heartbeat()
    assert fl.state is S.IDLE and not fl.airborne
    w.on_heartbeat()
    assert fl.state is S.IDLE and not [e for e in events if e["type"] in ("pilot_takeover", "failsafe")]


def test_armed_state_first_a_disarm_with_a_mode_change_is_not_a_pilot_takeover() -> None:
    w, fl, st, events = _watch(state=S.STREAMING, airborne=True)
    _hb(st, PX4_LAND, armed=False)  # PX4's fallback landed and disarmed (one heartbeat shows both)
    w.on_heartbeat()
    assert fl.state is S.IDLE
    kinds = [e["type"] for e in events]
    assert "pilot_takeover" not in kinds and "failsafe" in kinds


@pytest.mark.parametrize("stalled", [False, True])
def test_leaving_offboard_is_put_down_to_the_companion_when_it_stalled(stalled: bool) -> None:
    w, fl, st, events = _watch(stalled, S.STREAMING, airborne=True)
    _hb(st, PX4_LAND, armed=True)
    w.on_heartbeat()
    if stalled:
        assert fl.state is S.FAILSAFE
        assert next(e for e in events if e["type"] == "failsafe")["cause"] == "companion"
        assert not [e for e in events if e["type"] == "pilot_takeover"]
    else:
        assert fl.state is S.PILOT and [e for e in events if e["type"] == "pilot_takeover"]
    # then PX4 lands and disarms: the companion follows it out of FAILSAFE/PILOT
    _hb(st, PX4_OFFBOARD if stalled else PX4_LAND, armed=False)
    w.on_heartbeat()
    assert fl.state is S.IDLE


def test_check_link_says_nothing_while_the_companion_itself_stalled() -> None:
    w, fl, st, events = _watch(stalled=True)
    st.last_heartbeat = time.monotonic() - 10.0  # silence, as a loop that did not run sees it
    w.check_link()
    assert not fl.link_lost and not events


def _until(pred: Any, timeout: float = 5.0) -> bool:
    deadline = time.monotonic() + timeout
    while not pred():
        if time.monotonic() > deadline:
            return False
        time.sleep(0.01)
    return True


def test_the_setpoint_thread_withholds_setpoints_once_the_loop_stops_beating() -> None:
    """A real thread and clock: while the loop beats, setpoints leave; once it stops for the
    limit, none leaves (none sampled after the limit) until the loop releases them."""
    sent: list[float] = []
    ticks: list[Tick] = []
    live = Liveness(0.4)
    sender = SetpointSender(100.0, lambda sp: sent.append(time.monotonic()), YawPolicy("hold", 0.0, 0.3),
                            ticks.append, lambda exc: None)
    sender.liveness = live
    sender.feed = Feed(hold(np.zeros(3), 0.0), time.monotonic())
    stop = threading.Event()

    def loop() -> None:
        while not stop.is_set():
            live.beat()
            time.sleep(0.01)

    beater = threading.Thread(target=loop, daemon=True)
    beater.start()
    sender.start()
    try:
        assert _until(lambda: len(sent) >= 5) and not sender.withheld
        stop.set()  # the loop stalls
        beater.join()
        stalled_at = live.stamp
        assert _until(lambda: sender.withheld)
        assert live.withheld is not None and live.withheld[1] == "loop"
        # no setpoint sampled after the loop had been silent for the limit
        assert max(t.now for t in ticks if t.setpoint is not None) <= stalled_at + live.limit
        n = len(sent)
        live.beat()  # the loop is back: still withheld until it releases
        time.sleep(0.1)
        assert len(sent) == n
        assert live.release() is not None
        live.beat()
        assert _until(lambda: len(sent) > n, 0.3)
    finally:
        sender.stop()


def test_a_thread_stall_is_latched_when_the_stream_was_released_meanwhile() -> None:
    """The setpoint thread wakes THREAD_STALL late after a setpoint left, and the stream has been
    released meanwhile (the loop, first to run after the stall, saw the autopilot leave OFFBOARD
    for want of setpoints): the stall is still latched as the thread's, so the companion says
    that it stalled rather than leave the autopilot's failsafe unexplained. Seen in CI: a GIL
    held 1.25 s by another thread, no `stalled` event. Then, with no stream, a late wake-up
    latches nothing (nothing was flown)."""
    offset, armed, done = [0.0], threading.Event(), threading.Event()
    sent: list[float] = []
    sender: SetpointSender

    def clock() -> float:
        if armed.is_set() and not done.is_set():  # the stall and the release, as one step
            offset[0] += 1.0
            sender.feed = None
            done.set()
        return time.monotonic() + offset[0]

    live = Liveness(30.0, clock)  # the loop's own limit far off: this is about the thread
    sender = SetpointSender(100.0, lambda sp: sent.append(clock()), YawPolicy("hold", 0.0, 0.3),
                            lambda tick: None, lambda exc: None, clock=clock)
    sender.liveness = live
    sender.feed = Feed(hold(np.zeros(3), 0.0), clock())
    sender.start()
    try:
        assert _until(lambda: len(sent) >= 5) and not sender.withheld
        armed.set()
        assert _until(lambda: sender.withheld)
        assert live.withheld is not None and live.withheld[1] == "thread" and live.withheld[2] > 1.0
        assert live.release() is not None
        n = len(sent)
        armed.clear()
        done.clear()
        armed.set()  # another late wake-up, nothing streamed since: nothing to latch
        assert _until(done.is_set)
        time.sleep(0.1)
        assert live.withheld is None and len(sent) == n
    finally:
        sender.stop()


def _home_position(x: float, y: float, z: float, lat: float = 47.4, lon: float = 8.5) -> Any:
    from pymavlink.dialects.v20 import common as mav

    msg = mav.MAVLink_home_position_message(int(lat * 1e7), int(lon * 1e7), 488000, x, y, z,
                                            [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0, 0)
    msg._header = mav.MAVLink_header(mav.MAVLINK_MSG_ID_HOME_POSITION, 0, 0, 1, 1)
    return msg


def test_a_mission_is_refused_while_px4_reports_home_at_its_origin_whatever_the_geofence() -> None:
    """PX4 SIH before ready: HOME_POSITION at (0, 0, 0) while its estimate drifts 23-42 m; a
    mission is refused as 'not ready' with the geofence in either frame (the plan would start
    from the drifted position), and after a reboot the old home is no longer taken as valid."""
    st = VehicleState(autopilot="px4")
    st.take("HOME_POSITION", _home_position(0.0, 0.0, 0.0), 0.0, 1)
    assert st.home_pending and st.home is None
    for cfg in (CFG, config_with_fence()):
        err = read("mission", mission(), cfg, st.home, home_pending=st.home_pending)
        assert isinstance(err, MessageError) and "not ready" in err.reason and "obstacle" not in err.reason
    st.take("HOME_POSITION", _home_position(*HOME), 1.0, 1)  # ready
    assert not st.home_pending and st.home is not None and st.home_lla is not None
    assert isinstance(read("mission", mission(), config_with_fence(), st.home, home_pending=st.home_pending),
                      MissionSpec)
    st.take("HOME_POSITION", _home_position(0.0, 0.0, 0.0), 2.0, 1)  # rebooted: not ready again
    assert st.home_pending and st.home is None and st.home_lla is None
