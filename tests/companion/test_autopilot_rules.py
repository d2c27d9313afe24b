"""The autopilot watch's rules (companion.autopilot_rules.watch_step), on their own: which
supervisor event each reading makes, checked through the supervisor's `transition` where the
property is about what the flight state becomes (a pilot takeover, a failsafe put down to the
companion's stall, the link lost and restored, airborne by height)."""

from __future__ import annotations

import math
from dataclasses import replace
from typing import Any

from hypothesis import given, settings
from hypothesis import strategies as st

from companion.autopilot_rules import (
    AIR_HEIGHT,
    GROUND_FOR,
    GROUND_HEIGHT,
    GROUND_SPEED,
    LANDED_STATE_STALE,
    HeartbeatSeen,
    LandedStateSeen,
    LinkCheck,
    LinkFound,
    LinkRestored,
    NoteSeen,
    PositionSeen,
    Relay,
    WatchRules,
    WatchState,
    watch_step,
)
from companion.flight import IN_OUR_MODE, FlightState, State
from companion.supervisor import (
    Disarmed,
    GroundLearnt,
    Heartbeat,
    HeightReport,
    LandedStateReport,
    LinkLost,
    ModeReport,
    Say,
    transition,
)

RULES = WatchRules(sysid=7, compid=1, link_timeout=1.5)
OURS = {"px4": "OFFBOARD", "ardupilot": "GUIDED"}
MODES = st.sampled_from(["OFFBOARD", "GUIDED", "POSCTL", "ALTCTL", "LOITER", "AUTO.LAND", "RTL", "LAND", "STABILIZE",
                         "Mode(99)", ""])
AUTOPILOTS = st.sampled_from(["px4", "ardupilot"])
TIMES = st.floats(0.0, 1e6)


def hb(autopilot: str, mode: str, armed: bool = True, stalled: bool = False, sysid: int = 7,
       compid: int = 1) -> HeartbeatSeen:
    return HeartbeatSeen(autopilot, mode, armed, stalled, sysid, compid)


def pos(z: float, v: float = 0.0, armed: bool = True, landed_at: float = -math.inf) -> PositionSeen:
    return PositionSeen(0.0, 0.0, z, 0.0, 0.0, v, armed, landed_at, 7, 1)


def through(fs: FlightState, outputs: tuple[object, ...]) -> tuple[FlightState, list[object]]:
    """The supervisor's events among `outputs` applied in order: the state and the actions."""
    actions: list[object] = []
    for out in outputs:
        if not isinstance(out, LinkFound | LinkRestored | Relay):
            fs, acts = transition(fs, out)  # type: ignore[arg-type]
            actions.extend(acts)
    return fs, actions


def says(actions: list[object], kind: str) -> list[Say]:
    return [a for a in actions if isinstance(a, Say) and a.kind == kind]


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(sorted(IN_OUR_MODE, key=lambda s: s.value)), AUTOPILOTS, MODES, TIMES, st.booleans())
def test_a_mode_not_asked_for_while_in_control_is_a_pilot_takeover(state: State, autopilot: str, mode: str,
                                                                    now: float, exit_requested: bool) -> None:
    fs = FlightState(state, airborne=True, seen_link=True, exit_requested=exit_requested)
    ws, outs = watch_step(RULES, WatchState(), fs, hb(autopilot, mode), now)
    assert ws == WatchState() and outs[0] == Heartbeat()
    assert outs[-1] == ModeReport(mode == OURS[autopilot], mode, False)
    after, actions = through(fs, outs)
    taken = mode != OURS[autopilot] and not exit_requested
    assert (after.state is State.PILOT) == taken
    assert bool(says(actions, "pilot_takeover")) == taken and not says(actions, "failsafe")


@settings(max_examples=200, deadline=None)
@given(st.sampled_from(sorted(IN_OUR_MODE, key=lambda s: s.value)), AUTOPILOTS, MODES, st.booleans(), TIMES)
def test_a_heartbeat_after_a_stall_is_put_down_to_the_stall(state: State, autopilot: str, mode: str, armed: bool,
                                                            now: float) -> None:
    """Out of our mode, or disarmed, while the companion was stalled: a failsafe caused by the
    companion, never a pilot takeover."""
    fs = FlightState(state, airborne=True, seen_link=True)
    _ws, outs = watch_step(RULES, WatchState(), fs, hb(autopilot, mode, armed=armed, stalled=True), now)
    assert outs[-1] == (ModeReport(mode == OURS[autopilot], mode, True) if armed else Disarmed(mode, True))
    after, actions = through(fs, outs)
    assert not says(actions, "pilot_takeover")
    if not armed or mode != OURS[autopilot]:
        (said,) = says(actions, "failsafe")
        assert said.fields["cause"] == "companion" and after.state in (State.FAILSAFE, State.IDLE)
    else:
        assert after.state is state


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 255), st.integers(0, 255), st.data())
def test_no_event_from_a_message_of_another_system_or_component(sysid: int, compid: int, data: st.DataObject) -> None:
    if (sysid, compid) == (RULES.sysid, RULES.compid):
        sysid += 1
    reading: Any = data.draw(st.sampled_from([
        hb("px4", "POSCTL", sysid=sysid, compid=compid), hb("px4", "LAND", armed=False, sysid=sysid, compid=compid),
        PositionSeen(0.0, 0.0, -3.0, 0.0, 0.0, 0.0, True, -math.inf, sysid, compid),
        PositionSeen(0.0, 0.0, 0.0, 0.0, 0.0, 0.0, False, -math.inf, sysid, compid),
        LandedStateSeen(2, sysid, compid), NoteSeen("EVENT", 5, sysid, compid), NoteSeen("STATUSTEXT", None, sysid, compid)]))
    fs = data.draw(st.sampled_from([FlightState(State.STREAMING, True, seen_link=True, ground_z=0.0),
                                    FlightState(), FlightState(State.READY, seen_link=True, link_lost=True)]))
    ws = WatchState(on_ground_since=3.0, lost_at=1.0, event_seq=4)
    after, outs = watch_step(RULES, ws, fs, reading, data.draw(TIMES))
    assert outs == () and after is ws
    # the same reading from the autopilot makes something (here, where each of them does)
    fs = FlightState(State.STREAMING, False, seen_link=True, ground_z=0.0)
    assert watch_step(RULES, ws, fs, replace(reading, sysid=RULES.sysid, compid=RULES.compid), 10.0)[1]


def test_the_first_heartbeat_finds_the_link_and_one_after_a_loss_restores_it() -> None:
    fs = FlightState()
    ws, outs = watch_step(RULES, WatchState(), fs, hb("px4", "LOITER", armed=False), 5.0)
    assert outs == (Heartbeat(), LinkFound("px4", "LOITER"), Disarmed("LOITER", False))
    fs, _ = through(fs, outs)
    assert fs.seen_link and not fs.link_lost
    # silence past the link timeout, while flying ours: lost, and a failsafe
    fs = replace(fs, state=State.STREAMING, airborne=True)
    quiet = LinkCheck(last_heartbeat=5.0, last_message=5.2, stalled=False)
    assert watch_step(RULES, ws, fs, quiet, 5.2 + RULES.link_timeout) == (ws, ())  # not yet: any message counts
    ws, outs = watch_step(RULES, ws, fs, quiet, 7.0)
    assert outs == (LinkLost(RULES.link_timeout),) and ws.lost_at == 7.0
    fs, actions = through(fs, outs)
    assert fs.link_lost and fs.state is State.FAILSAFE and says(actions, "link_lost")
    assert watch_step(RULES, ws, fs, quiet, 9.0) == (ws, ())  # lost once, said once
    ws2, outs = watch_step(RULES, ws, fs, hb("px4", "POSCTL"), 11.0)
    assert outs == (Heartbeat(), LinkRestored(11.0 - 7.0 + RULES.link_timeout, "POSCTL", True),
                    ModeReport(False, "POSCTL", False)) and ws2 == ws
    fs, _ = through(fs, outs)
    assert not fs.link_lost and fs.state is State.FAILSAFE  # control is not retaken without `start`


@settings(max_examples=200, deadline=None)
@given(st.floats(0.0, 100.0), st.floats(0.0, 100.0), TIMES, st.booleans(), st.booleans(), st.booleans())
def test_the_link_is_lost_only_after_the_timeout_seen_by_a_companion_that_ran(
        hb_ago: float, msg_ago: float, now: float, stalled: bool, seen: bool, lost: bool) -> None:
    fs = FlightState(State.READY, seen_link=seen, link_lost=lost)
    ws, outs = watch_step(RULES, WatchState(), fs, LinkCheck(now - hb_ago, now - msg_ago, stalled), now)
    silent = now - max(now - hb_ago, now - msg_ago) > RULES.link_timeout
    expected = seen and not lost and not stalled and silent
    assert outs == ((LinkLost(RULES.link_timeout),) if expected else ())
    assert ws.lost_at == (now if expected else -math.inf)
    # never heard: nothing to lose
    assert watch_step(RULES, WatchState(), FlightState(), LinkCheck(-math.inf, now, False), now)[1] == ()


@given(st.integers(0, 5))
def test_the_landed_state_in_two_facts(landed: int) -> None:
    ws = WatchState(on_ground_since=2.0)
    after, outs = watch_step(RULES, ws, FlightState(), LandedStateSeen(landed, 7, 1), 1.0)
    assert after is ws and outs == (LandedStateReport(in_air=landed in (2, 4), on_ground=landed == 1),)


def test_a_resent_event_is_relayed_once_and_statustext_always() -> None:
    ws, outs = watch_step(RULES, WatchState(), FlightState(), NoteSeen("EVENT", 12, 7, 1), 0.0)
    assert outs == (Relay("EVENT"),) and ws.event_seq == 12
    assert watch_step(RULES, ws, FlightState(), NoteSeen("EVENT", 12, 7, 1), 0.1) == (ws, ())
    assert watch_step(RULES, ws, FlightState(), NoteSeen("EVENT", 13, 7, 1), 0.2)[1] == (Relay("EVENT"),)
    for _ in range(2):
        assert watch_step(RULES, ws, FlightState(), NoteSeen("STATUSTEXT", None, 7, 1), 0.3) == (ws, (Relay("STATUSTEXT"),))


def test_disarmed_the_ground_is_learnt_and_the_rest_timer_cleared() -> None:
    ws, outs = watch_step(RULES, WatchState(on_ground_since=4.0), FlightState(), pos(0.3, armed=False), 5.0)
    assert outs == (GroundLearnt(0.3),) and ws.on_ground_since == math.inf
    # no position estimate (NaN): nothing at all
    ws = WatchState(on_ground_since=4.0)
    assert watch_step(RULES, ws, FlightState(), pos(math.nan, armed=False), 5.0) == (ws, ())


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.sampled_from([-2.0, -0.6, -0.5, -0.4, -0.3, -0.2, 0.0, 0.2]) | st.floats(-5.0, 1.0),
                          st.sampled_from([0.0, 0.1, 0.2, 0.5]) | st.floats(0.0, 2.0)), min_size=1, max_size=40),
       st.booleans(), st.sampled_from([State.PILOT, State.READY, State.HOLDING, State.ARMING, State.TAKEOFF]))
def test_airborne_by_height_follows_its_thresholds(samples: list[tuple[float, float]], airborne: bool,
                                                   state: State) -> None:
    """Without a landed state: above AIR_HEIGHT is airborne at once; low and slow for GROUND_FOR
    is on the ground; our own takeoff decides itself; nothing while a landed state is fresh."""
    fs = FlightState(state, airborne, seen_link=True, ground_z=0.0)
    ws = WatchState()
    rest_since = math.inf
    for k, (z, v) in enumerate(samples):
        now = 10.0 + 0.25 * k
        fresh = watch_step(RULES, ws, fs, pos(z, v, landed_at=now - LANDED_STATE_STALE / 2), now)
        assert fresh == (ws, ())
        ws, outs = watch_step(RULES, ws, fs, pos(z, v), now)
        height = -z
        if state in (State.ARMING, State.TAKEOFF):
            assert outs == () and ws == WatchState()
            continue
        if height > AIR_HEIGHT:
            rest_since = math.inf
            assert outs == (() if fs.airborne else (HeightReport(True),))
        elif height < GROUND_HEIGHT and v < GROUND_SPEED:
            rest_since = min(rest_since, now)
            landed = fs.airborne and now - rest_since >= GROUND_FOR
            assert outs == ((HeightReport(False),) if landed else ())
        else:
            rest_since = math.inf
            assert outs == ()
        assert ws.on_ground_since == rest_since
        fs, _ = through(fs, outs)


def test_at_rest_on_the_ground_for_ground_for_is_landed() -> None:
    fs = FlightState(State.PILOT, True, seen_link=True, ground_z=0.0)
    ws, outs = watch_step(RULES, WatchState(), fs, pos(0.1, 0.05), 20.0)
    assert outs == () and ws.on_ground_since == 20.0
    ws, outs = watch_step(RULES, ws, fs, pos(0.1, 0.05), 20.0 + GROUND_FOR * 0.5)
    assert outs == () and ws.on_ground_since == 20.0
    assert watch_step(RULES, ws, fs, pos(0.1, 0.05), 20.0 + GROUND_FOR)[1] == (HeightReport(False),)
    # moving, or at GROUND_HEIGHT: the rest starts again
    assert watch_step(RULES, ws, fs, pos(0.1, GROUND_SPEED), 22.0) == (WatchState(), ())
    assert watch_step(RULES, ws, fs, pos(-GROUND_HEIGHT, 0.0), 22.0) == (WatchState(), ())


@settings(max_examples=100, deadline=None)
@given(st.sampled_from(list(State)), st.booleans(), st.booleans(), st.booleans(), AUTOPILOTS, MODES, TIMES)
def test_the_rules_are_a_function_of_their_inputs(state: State, airborne: bool, armed: bool, stalled: bool,
                                                  autopilot: str, mode: str, now: float) -> None:
    """The same inputs, the same outputs, and the inputs untouched (what replay relies on)."""
    fs = FlightState(state, airborne, seen_link=True, ground_z=0.0)
    ws = WatchState(on_ground_since=now - 0.5, lost_at=now - 3.0, event_seq=1)
    for reading in (hb(autopilot, mode, armed, stalled), pos(-1.0, 0.1, armed), LinkCheck(now - 9, now - 9, stalled)):
        first, again = watch_step(RULES, ws, fs, reading, now), watch_step(RULES, ws, fs, reading, now)
        assert first == again
    assert ws == WatchState(on_ground_since=now - 0.5, lost_at=now - 3.0, event_seq=1)
