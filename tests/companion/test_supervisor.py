"""The supervisor's transition function, driven directly: random sequences of events, with
the invariants of the flight state checked after each one."""

from __future__ import annotations

import dataclasses
from dataclasses import replace
from typing import Any

import pytest
from hypothesis import settings
from hypothesis import strategies as st
from hypothesis.stateful import RuleBasedStateMachine, invariant, rule

from companion.flight import (
    ALLOWED,
    IN_OUR_MODE,
    FlightState,
    IllegalTransition,
    State,
)
from companion.supervisor import (
    Announce,
    Armed,
    ArmRequested,
    Braking,
    ControlTaken,
    ControlTakenBack,
    Disarmed,
    DisarmedOnCommand,
    DisarmRequested,
    Event,
    ExitBegan,
    ExitRequested,
    GroundLearnt,
    HandedOver,
    Heartbeat,
    HeightReport,
    LandedStateReport,
    LandRequested,
    LinkLost,
    MissionComplete,
    MissionStarted,
    ModeReport,
    Release,
    ReplanFlown,
    Say,
    SequenceAborted,
    Stalled,
    StartBegan,
    StartEnded,
    StoppedAfterBraking,
    StopStream,
    Supervisor,
    TakeoffBegan,
    TakeoffInterrupted,
    TakingControl,
    TookOff,
    transition,
)

S = State
reasons = st.text(st.characters(categories=["L", "N"]), min_size=1, max_size=12)
modes = st.sampled_from(["OFFBOARD", "GUIDED", "LOITER", "LAND", "POSCTL", "STABILIZE", "BRAKE"])

# What the autopilot, the link or a stall say, and the requests whose target every state
# allows: never a bug of the caller, so they never raise.
NEVER_RAISE = (ControlTaken, ExitRequested, ArmRequested, DisarmRequested, StartBegan, StartEnded, Heartbeat,
               GroundLearnt, LandedStateReport, HeightReport, Disarmed, ModeReport, LinkLost, Stalled,
               TakeoffInterrupted, SequenceAborted, ExitBegan, LandRequested, DisarmedOnCommand, HandedOver,
               MissionComplete, StoppedAfterBraking)
# The autopilot's and the link's reports: none of them ever puts us in control.
REPORTS = (Heartbeat, GroundLearnt, LandedStateReport, HeightReport, Disarmed, ModeReport, LinkLost)
# The only ways out of PILOT: our own start/arm (which begins by taking control), a disarm
# (the autopilot's or ours, on the ground), a landing (ours, or a hand-over to LAND).
LEAVE_PILOT = (TakingControl, Disarmed, DisarmedOnCommand, LandRequested, HandedOver)

events: st.SearchStrategy[Event] = st.one_of(
    st.builds(ControlTaken), st.builds(ExitRequested), st.builds(ArmRequested), st.builds(DisarmRequested),
    st.builds(StartBegan), st.builds(StartEnded), st.builds(Heartbeat),
    st.builds(GroundLearnt, st.floats(-5, 5)),
    st.builds(LandedStateReport, st.booleans(), st.booleans()),
    st.builds(HeightReport, st.booleans()),
    st.builds(Disarmed, modes, st.booleans()),
    st.builds(ModeReport, st.booleans(), modes, st.booleans()),
    st.builds(LinkLost, st.just(1.5)), st.builds(Stalled, reasons),
    st.builds(TakingControl, reasons), st.builds(Armed, modes), st.builds(ControlTakenBack, modes),
    st.builds(TakeoffBegan, reasons), st.builds(TookOff, reasons), st.builds(TakeoffInterrupted, reasons),
    st.builds(SequenceAborted, reasons, st.booleans()), st.builds(ExitBegan, reasons, st.booleans()),
    st.builds(LandRequested), st.builds(DisarmedOnCommand, reasons),
    st.builds(HandedOver, reasons, modes, st.booleans()),
    st.builds(MissionStarted, reasons), st.builds(ReplanFlown, reasons), st.builds(MissionComplete, reasons),
    st.builds(StoppedAfterBraking), st.builds(Braking, reasons),
)


class FlightMachine(RuleBasedStateMachine):
    def __init__(self) -> None:
        super().__init__()
        self.fs = FlightState()

    @rule(event=events)
    def submit(self, event: Event) -> None:
        before = self.fs
        if isinstance(event, TakingControl) and before.refuse("arm", armed=False, auto_arm=True,
                                                              has_mission=True) is not None:
            return  # a command the companion refuses never begins (Commands checks first)
        try:
            after, actions = transition(before, event)
        except IllegalTransition:
            assert not isinstance(event, NEVER_RAISE), f"{event} raised in {before}"
            return
        self.check_step(before, event, after, actions)
        self.fs = after

    def check_step(self, before: FlightState, event: Event, after: FlightState, actions: tuple[Any, ...]) -> None:
        announced = [a for a in actions if isinstance(a, Announce)]
        if after.state is before.state:
            assert not announced, f"{event}: an announcement without a transition"
        else:
            assert after.state in ALLOWED[before.state], f"{event}: {before.state} -> {after.state} returned"
            assert announced == [Announce(before.state, after.state, announced[0].reason)]
            assert announced[0].reason.strip(), f"{event}: a transition without a reason"
        if any(isinstance(a, (Release, StopStream)) for a in actions):
            # stopping is always said, and leaves us out of control
            assert announced and not after.controlling, f"{event}: stopped without leaving control"
        if before.state is S.PILOT and after.state is not S.PILOT:
            assert isinstance(event, LEAVE_PILOT), f"{event} left PILOT"
            assert after.state in (S.ARMING, S.IDLE, S.LANDING), f"{event}: PILOT -> {after.state}"
        if isinstance(event, REPORTS):
            assert not (after.controlling and not before.controlling), f"{event} put us in control"
        if isinstance(event, LinkLost):
            assert after.link_lost and not after.controlling
            assert (Release() in actions) == before.controlling
            assert [a.kind for a in actions if isinstance(a, Say)] == ["link_lost"]
        if isinstance(event, (ModeReport, Disarmed)) and before.state in IN_OUR_MODE and after.state != before.state:
            assert Release() in actions, f"{event}: left our mode without stopping"
        if isinstance(event, (Disarmed, DisarmedOnCommand)) and after.state is not before.state:
            assert not after.airborne, f"{event}: still airborne after a disarm"
        assert after.seen_link or not before.seen_link, f"{event} forgot the link was seen"
        if isinstance(event, Stalled) and before.controlling:
            assert after.state is S.FAILSAFE and Release() in actions

    @invariant()
    def never_in_control_with_the_link_lost(self) -> None:
        # neither a report (check_step) nor a command (refused while the link is lost) brings
        # the state into control before a heartbeat comes back
        assert not (self.fs.link_lost and self.fs.controlling)



TestFlightMachine = FlightMachine.TestCase
TestFlightMachine.settings = settings(max_examples=300, stateful_step_count=40, deadline=None)


def test_the_state_is_frozen() -> None:
    fs = FlightState()
    with pytest.raises(dataclasses.FrozenInstanceError):
        fs.state = S.STREAMING  # type: ignore[misc]


def test_the_supervisor_carries_out_the_actions_in_order_with_the_new_state_in_place() -> None:
    sup = Supervisor(FlightState(S.STREAMING, airborne=True, seen_link=True))
    done: list[tuple[str, State]] = []
    sup.connect(announce=lambda a: done.append(("announce", sup.state)),
                say=lambda a: done.append((a.kind, sup.state)),
                release=lambda: done.append(("release", sup.state)))
    actions = sup.handle(ModeReport(in_our_mode=False, mode="POSCTL", stalled=False))
    assert [type(a) for a in actions] == [Release, Announce, Say]
    assert done == [("release", S.PILOT), ("announce", S.PILOT), ("pilot_takeover", S.PILOT)]
    assert sup.history == [{"type": "state", "from": "STREAMING", "to": "PILOT",
                            "message": "autopilot left the offboard/guided mode without our request (mode POSCTL)"}]
    assert sup.handle(ModeReport(in_our_mode=False, mode="POSCTL", stalled=False)) == ()


def test_a_disarm_we_asked_for_is_not_a_failsafe() -> None:
    fs = FlightState(S.READY, airborne=False)
    fs, _ = transition(fs, DisarmRequested())
    after, actions = transition(fs, Disarmed("OFFBOARD", stalled=False))
    assert after == fs and actions == ()  # the command itself moves to IDLE once the autopilot agrees
    after, actions = transition(FlightState(S.READY, airborne=True), Disarmed("OFFBOARD", stalled=True))
    assert after.state is S.IDLE and not after.airborne
    assert [a.fields["cause"] for a in actions if isinstance(a, Say)] == ["companion"]


def test_a_mode_change_we_asked_for_is_not_a_takeover() -> None:
    fs, _ = transition(FlightState(S.HOLDING, airborne=True), ExitRequested())
    assert transition(fs, ModeReport(False, "LOITER", stalled=False)) == (fs, ())
    fs, _ = transition(fs, ControlTaken())  # streaming again: the next change is not ours
    assert transition(fs, ModeReport(False, "LOITER", stalled=False))[0].state is S.PILOT


def test_only_our_takeoff_decides_airborne_during_it() -> None:
    fs = FlightState(S.TAKEOFF)
    assert transition(fs, HeightReport(airborne=True)) == (fs, ())
    assert transition(fs, LandedStateReport(in_air=False, on_ground=True)) == (fs, ())
    assert transition(fs, LandedStateReport(in_air=True, on_ground=False))[0].airborne
    after, _ = transition(fs, TookOff("airborne at 2 m"))
    assert after.state is S.READY and after.airborne


@pytest.mark.parametrize("command", ["arm", "takeoff", "start", "resume"])
def test_commands_that_take_control_are_refused_while_the_link_is_lost(command: str) -> None:
    lost = FlightState(S.FAILSAFE, airborne=True, seen_link=True, link_lost=True)
    why = lost.refuse(command, armed=True, auto_arm=True, has_mission=True)
    assert why is not None and "link" in why
    assert replace(lost, link_lost=False).refuse(command, armed=True, auto_arm=True, has_mission=True) != why


@pytest.mark.parametrize("command", ["hold", "land", "abort", "disarm"])
def test_commands_that_stop_are_still_tried_while_the_link_is_lost(command: str) -> None:
    lost = FlightState(S.STREAMING, airborne=True, seen_link=True, link_lost=True)
    why = lost.refuse(command, armed=True, auto_arm=True, has_mission=True)
    assert why is None or "link" not in why

