"""The trim (companion.trim): a slow horizontal integral of the tracking error added to the
setpoints' position, never longer than its limit (within the tracking allowance), held when no
plan is flown in the air, dropped when the companion stops streaming; and what the senders do
with it (the position moved by exactly the trim, velocity and acceleration the plan's)."""

from __future__ import annotations

import socket
import threading
import time

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from companion.sendproc import Encoding, SetpointProcess
from companion.setpoints import Feed, SetpointSender, Tick, YawPolicy, sample
from companion.trim import DT_MAX, Trim, TrimRules, TrimSample, trim_step
from planner_core import Trajectory

RULES = TrimRules(tc=2.0, limit=0.5)


def _sample(at: float, err: tuple[float, float, float], integrate: bool = True, streaming: bool = True) -> TrimSample:
    return TrimSample(at, np.array(err, dtype=float), integrate, streaming)


def test_a_constant_error_is_integrated_horizontally_at_one_over_tc_up_to_the_limit() -> None:
    trim = Trim()
    err = (0.2, -0.1, 0.3)  # the vertical error is never trimmed
    for k in range(0, 501):  # 50 Hz for 10 s
        trim = trim_step(RULES, trim, _sample(k * 0.02, err))
        t = k * 0.02
        want = np.array([0.2, -0.1]) * t / RULES.tc
        if np.hypot(*want) <= RULES.limit - 1e-9:
            assert np.allclose(trim.offset[:2], want, atol=1e-9), (t, trim.offset)
        assert trim.offset[2] == 0.0
    # saturated along the error's direction, at the limit
    assert np.isclose(np.hypot(*trim.offset[:2]), RULES.limit)
    assert np.allclose(trim.offset[:2] / RULES.limit, np.array([0.2, -0.1]) / np.hypot(0.2, -0.1))


def test_off_not_streaming_and_held() -> None:
    off = TrimRules(tc=0.0, limit=0.5)
    assert not np.any(trim_step(off, Trim(), _sample(1.0, (1.0, 1.0, 0.0))).offset)
    trim = Trim()
    for k in range(100):
        trim = trim_step(RULES, trim, _sample(k * 0.02, (0.3, 0.0, 0.0)))
    assert trim.offset[0] > 0.2
    # no plan flown in the air (a takeoff, a landing, on the ground): held, not integrated
    held = trim_step(RULES, trim, _sample(2.5, (5.0, 5.0, 0.0), integrate=False))
    assert np.array_equal(held.offset, trim.offset) and held.at is None
    # the first sample after a pause integrates nothing (no time since the last one counted)
    again = trim_step(RULES, held, _sample(30.0, (0.3, 0.0, 0.0)))
    assert np.array_equal(again.offset, trim.offset)
    # a measurement that is not a number is not integrated
    nan = trim_step(RULES, again, _sample(30.02, (float("nan"), 0.0, 0.0)))
    assert np.array_equal(nan.offset, trim.offset)
    # the companion stops streaming: dropped
    gone = trim_step(RULES, trim, _sample(3.0, (0.3, 0.0, 0.0), streaming=False))
    assert not np.any(gone.offset) and gone.at is None


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.floats(0.0, 1.0), st.floats(-20.0, 20.0), st.floats(-20.0, 20.0),
                          st.floats(-20.0, 20.0), st.booleans(), st.booleans()), min_size=1, max_size=60),
       st.floats(0.05, 10.0), st.floats(0.0, 2.0))
def test_the_trim_never_exceeds_its_limit_nor_moves_faster_than_the_error_allows(
        steps: list[tuple[float, float, float, float, bool, bool]], tc: float, limit: float) -> None:
    rules = TrimRules(tc, limit)
    trim, at = Trim(), 0.0
    for gap, ex, ey, ez, integrate, streaming in steps:
        at += gap
        err = np.array([ex, ey, ez])
        nxt = trim_step(rules, trim, TrimSample(at, err, integrate, streaming))
        assert np.hypot(nxt.offset[0], nxt.offset[1]) <= limit + 1e-12
        assert nxt.offset[2] == 0.0
        if not streaming:
            assert not np.any(nxt.offset)
        elif rules.on:
            # one sample moves it by at most the error times its (capped) interval over tc
            step = float(np.hypot(*(nxt.offset - trim.offset)[:2]))
            assert step <= np.hypot(ex, ey) * DT_MAX / tc + 1e-9
        trim = nxt


def _line() -> Trajectory:
    u = np.linspace(0.0, 1.0, 10)
    ctrl = np.zeros((1, 10, 3))
    ctrl[0, :, 0] = 100.0 * u  # 1 m/s along x for 100 s
    ctrl[0, :, 2] = -2.0
    return Trajectory(np.array([0.0, 100.0]), ctrl)


def test_sample_moves_the_position_by_the_trim_only() -> None:
    yaw = YawPolicy("fixed", 0.0, 0.3)
    trim = np.array([0.2, -0.3, 0.0])
    for k, tc in ((0.0, 0.0), (0.09, 1.0)):
        plain, trimmed = sample(_line(), 7.5, yaw, k, tc), sample(_line(), 7.5, yaw, k, tc, trim)
        assert np.allclose(trimmed.position - plain.position, trim, atol=1e-12)
        assert np.array_equal(trimmed.velocity, plain.velocity)
        assert np.array_equal(trimmed.acceleration, plain.acceleration)


def test_both_senders_send_the_trim_they_are_given() -> None:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    ticks: list[Tick] = []
    lock = threading.Lock()

    def on_tick(tick: Tick) -> None:
        with lock:
            ticks.append(tick)

    trim = np.array([0.25, -0.1, 0.0])
    proc = SetpointProcess(50.0, lambda: (sock.fileno(), True, Encoding(255, 191, 1, 1, None, time.monotonic())),
                           YawPolicy("fixed", 0.0, 0.3), on_tick, lambda exc: None)
    thread = SetpointSender(50.0, lambda sp: None, YawPolicy("fixed", 0.0, 0.3), on_tick, lambda exc: None)
    for sender in (proc, thread):
        sender.start()
        try:
            t_base = time.monotonic()
            sender.feed = Feed(_line(), t_base)
            time.sleep(0.3)
            sender.trim = trim
            time.sleep(0.1)
            mark = time.monotonic()
            time.sleep(0.3)
            sender.trim = None
            time.sleep(0.1)
            after = time.monotonic()
            time.sleep(0.3)
            with lock:
                got = [t for t in ticks if t.setpoint is not None]
                ticks.clear()
            on = [t for t in got if mark <= t.now <= after - 0.1]
            gone = [t for t in got if t.now > after]
            assert len(on) >= 5 and len(gone) >= 5
            # x is the plan's (1 m/s, lead 0) plus the trim; then the plan's again
            assert np.allclose([t.setpoint.position[0] - (t.now - t_base) for t in on], trim[0], atol=1e-6)
            assert np.allclose([t.setpoint.position[1] for t in on], trim[1], atol=1e-6)
            assert np.allclose([t.setpoint.position[0] - (t.now - t_base) for t in gone], 0.0, atol=1e-6)
            assert np.allclose([t.setpoint.velocity[0] for t in on], 1.0, atol=1e-6)
        finally:
            sender.stop()
    sock.close()
