"""Issue 24.2: a vehicle's clock measured against the fleet's from the others' trajectory puts
(companion.clocks): never a false alarm while the assumptions hold, always found beyond them,
and the odd one out is the one that stops."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.clocks import MIN_SAMPLES, WINDOW, ClockCheck

TOL, DELAY = 0.05, 0.1


def hear(check: ClockCheck, vehicle: str, ours_minus_theirs: float, delays: list[float], t0: float = 1000.0) -> None:
    """`vehicle` publishes once a second; each put takes its delay to arrive."""
    for k, d in enumerate(delays):
        sent_theirs = t0 + k - ours_minus_theirs  # their clock reads ours - offset
        check.heard(vehicle, sent_theirs, t0 + k + d)


@settings(max_examples=200, deadline=None)
@given(offset=st.floats(-TOL, TOL), delays=st.lists(st.floats(0.0, DELAY), min_size=1, max_size=40))
def test_no_alarm_while_the_clocks_agree_and_the_delays_are_bounded(offset: float, delays: list[float]) -> None:
    check = ClockCheck(TOL, DELAY)
    hear(check, "a", offset, delays)
    now = 1000.0 + len(delays)
    o = check.offsets(now)["a"]
    assert o.lo - 1e-9 <= offset <= o.hi + 1e-9  # the interval holds the true offset
    assert not o.disagrees(TOL)
    assert check.ours_off(now) is None and check.others_off(now) == []


@settings(max_examples=200, deadline=None)
@given(excess=st.floats(1e-3, 5.0), sign=st.sampled_from([-1.0, 1.0]),
       delays=st.lists(st.floats(0.0, DELAY), min_size=MIN_SAMPLES, max_size=40))
def test_a_clock_off_by_more_than_tolerance_and_delay_is_always_found(excess: float, sign: float,
                                                                      delays: list[float]) -> None:
    offset = sign * (TOL + DELAY + excess)
    check = ClockCheck(TOL, DELAY)
    hear(check, "a", offset, delays)
    now = 1000.0 + len(delays)
    assert check.offsets(now)["a"].disagrees(TOL)
    assert check.others_off(now) == ["a"]
    # one other vehicle: neither can tell whose clock it is, so both stop
    assert check.ours_off(now) is not None


def test_the_odd_one_out_stops_and_the_others_fly_on() -> None:
    rng = np.random.default_rng(1)
    clocks = {"a": 0.0, "b": 0.01, "c": -0.02, "d": 0.4}  # d's clock is 0.4 s ahead
    checks = {v: ClockCheck(TOL, DELAY) for v in clocks}
    for me, check in checks.items():
        for other, theirs in clocks.items():
            if other != me:
                hear(check, other, clocks[me] - theirs, list(rng.uniform(0.0, DELAY, 10)))
    now = 1010.0
    assert checks["d"].ours_off(now) is not None
    assert "3 of the 3" in str(checks["d"].ours_off(now))
    for v in "abc":
        assert checks[v].ours_off(now) is None, v
        assert checks[v].others_off(now) == ["d"]


def test_too_few_samples_or_old_ones_do_not_count() -> None:
    check = ClockCheck(TOL, DELAY)
    hear(check, "a", 1.0, [0.0] * (MIN_SAMPLES - 1))
    assert check.ours_off(1000.0 + MIN_SAMPLES) is None  # not enough yet
    hear(check, "a", 1.0, [0.0] * MIN_SAMPLES)
    assert check.ours_off(1000.0 + MIN_SAMPLES) is not None
    # the clock put right: the old samples leave the window and the verdict with them
    hear(check, "a", 0.0, [0.0] * MIN_SAMPLES, t0=1000.0 + WINDOW + 10)
    assert check.ours_off(1000.0 + WINDOW + 10 + MIN_SAMPLES) is None


def test_late_puts_move_nothing_unless_every_one_is_late() -> None:
    check = ClockCheck(TOL, DELAY)
    hear(check, "a", 0.0, [0.0] * MIN_SAMPLES + [2.0, 0.5])  # a busy moment: two puts late
    assert check.others_off(1000.0 + MIN_SAMPLES + 2) == []
    check = ClockCheck(TOL, DELAY)
    hear(check, "a", 0.0, [0.3] * MIN_SAMPLES)  # every put of the window later than max_delay + tolerance
    assert check.others_off(1000.0 + MIN_SAMPLES) == ["a"]
