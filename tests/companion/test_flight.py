from __future__ import annotations

import pytest

from companion.flight import (
    ALLOWED,
    CONTROLLING,
    FlightState,
    IllegalTransition,
    State,
    go,
    on_link,
    on_mode_report,
    refuse_command,
)

S = State


def test_nominal_sequence_emits_events_with_reasons() -> None:
    f = FlightState()
    history = []
    path = [S.ARMING, S.TAKEOFF, S.READY, S.STREAMING, S.HOLDING, S.STREAMING, S.BRAKING, S.HOLDING, S.LANDING, S.IDLE]
    for to in path:
        f, ev = go(f, to, f"to {to.value}")
        assert ev is not None and ev["to"] == to.value and ev["message"] == f"to {to.value}"
        history.append(ev)
    assert [e["to"] for e in history] == [s.value for s in path]
    assert go(f, S.IDLE, "again") == (f, None)


@pytest.mark.parametrize(("src", "dst"), [(S.IDLE, S.STREAMING), (S.PILOT, S.STREAMING), (S.LANDING, S.STREAMING),
                                          (S.IDLE, S.READY), (S.FAILSAFE, S.HOLDING)])
def test_illegal_transitions_raise(src: State, dst: State) -> None:
    f = FlightState(src)
    with pytest.raises(IllegalTransition):
        go(f, dst, "no")
    assert f.state is src


def test_every_state_can_fall_back_to_pilot_or_idle() -> None:
    for s, targets in ALLOWED.items():
        if s is not S.PILOT:
            assert S.PILOT in targets or s is S.IDLE or S.IDLE in targets


def test_pilot_takeover_only_when_we_did_not_ask() -> None:
    assert on_mode_report(S.STREAMING, in_our_mode=False, requested_exit=False) is not None
    assert on_mode_report(S.STREAMING, in_our_mode=False, requested_exit=True) is None
    assert on_mode_report(S.STREAMING, in_our_mode=True, requested_exit=False) is None
    # ARMING streams before OFFBOARD is granted: not being in OFFBOARD yet is expected.
    assert on_mode_report(S.ARMING, in_our_mode=False, requested_exit=False) is None
    assert on_mode_report(S.IDLE, in_our_mode=False, requested_exit=False) is None


def test_link_loss_is_a_failsafe_only_while_controlling() -> None:
    for s in State:
        r = on_link(s, link_ok=False)
        assert (r is not None) == (s in CONTROLLING)
        assert on_link(s, link_ok=True) is None


def test_arm_policy() -> None:
    assert refuse_command(S.IDLE, "takeoff", armed=False, auto_arm=False, has_mission=False) is not None
    assert refuse_command(S.IDLE, "takeoff", armed=False, auto_arm=True, has_mission=False) is None
    assert "no mission" in refuse_command(S.READY, "start", armed=True, auto_arm=False, has_mission=False)
    assert refuse_command(S.IDLE, "start", armed=False, auto_arm=False, has_mission=True) is not None
    assert refuse_command(S.PILOT, "start", armed=True, auto_arm=False, has_mission=True) is None
    assert refuse_command(S.FAILSAFE, "start", armed=True, auto_arm=False, has_mission=False) is None
    assert refuse_command(S.IDLE, "hold", armed=True, auto_arm=False, has_mission=True) is not None
    assert refuse_command(S.IDLE, "disarm", armed=False, auto_arm=False, has_mission=False) is not None
    assert refuse_command(S.STREAMING, "abort", armed=True, auto_arm=False, has_mission=True) is None
