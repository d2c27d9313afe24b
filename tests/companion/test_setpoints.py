from __future__ import annotations

import asyncio
import time

import numpy as np
import pytest

from companion.setpoints import DeadlineScheduler, YawPolicy, hold_trajectory, sample, sleep_until


def test_kth_deadline_is_t0_plus_k_over_rate_without_drift() -> None:
    s = DeadlineScheduler(t0=100.0, rate=50.0)
    now = 100.0
    for k in range(1, 100_001):
        d = s.next_deadline(now)
        assert d == 100.0 + k / 50.0
        now = d + 0.013  # always late by most of a period: no accumulation
    assert s.k == 100_000


def test_late_wakeups_skip_missed_ticks_on_the_grid() -> None:
    s = DeadlineScheduler(t0=0.0, rate=100.0)
    # Woken at 5.55 periods: ticks 1..4 are dropped, tick 5 (less than a period
    # late) is sent at once, and the grid continues at 0.06.
    d = s.next_deadline(0.0555)
    assert d == pytest.approx(0.05) and s.k == 5
    assert s.next_deadline(0.0556) == pytest.approx(0.06)


def test_sleep_until_does_not_wake_early() -> None:
    async def run() -> list[float]:
        t0 = time.monotonic()
        s = DeadlineScheduler(t0, 100.0)
        late = []
        for _ in range(20):
            d = s.next_deadline(time.monotonic())
            now = await sleep_until(d)
            late.append(now - d)
        return late

    late = asyncio.run(run())
    assert min(late) >= 0.0


def test_hold_and_yaw() -> None:
    h = hold_trajectory(np.array([1.0, 2.0, -3.0]), 5.0)
    yaw = YawPolicy("velocity", 0.5, 0.3)
    for t in (0.0, 5.0, 5.5, 100.0):
        sp = sample(h, t, yaw)
        assert sp.position.tolist() == [1.0, 2.0, -3.0]
        assert not sp.velocity.any() and not sp.acceleration.any()
        assert sp.yaw == 0.5  # too slow to define a heading: keep the last
    assert yaw(np.array([0.0, 1.0, 0.0])) == pytest.approx(np.pi / 2)
    assert YawPolicy("fixed", 0.2, 0.3)(np.array([1.0, 1.0, 0.0])) == 0.2


def test_yaw_modes_start_from_the_measured_heading() -> None:
    hold = YawPolicy("hold", 0.0, 0.3)
    hold.reset(1.2)
    assert hold(np.array([3.0, 0.0, 0.0])) == 1.2
    fixed = YawPolicy("fixed", 0.4, 0.3)
    fixed.reset(1.2)
    assert fixed(np.array([0.0, 0.0, 0.0])) == 0.4
    vel = YawPolicy("velocity", 0.0, 0.3)
    vel.reset(-0.5)
    assert vel(np.array([0.1, 0.0, 0.0])) == -0.5
    assert vel(np.array([0.0, -2.0, 0.0])) == pytest.approx(-np.pi / 2)
