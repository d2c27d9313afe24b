"""What the service hands its setpoint thread, and what it does with each tick."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest

from companion.config import Config
from companion.service import Service
from companion.setpoints import Feed, Setpoint, Tick, hold_trajectory


class FeedLog:
    """Stands in for the SetpointSender: records every feed the service publishes."""

    def __init__(self) -> None:
        self.history: list[Feed | None] = []

    @property
    def feed(self) -> Feed | None:
        return self.history[-1] if self.history else None

    @feed.setter
    def feed(self, value: Feed | None) -> None:
        self.history.append(value)


@pytest.fixture
def svc() -> Iterator[Service]:
    s = Service(Config())
    yield s
    for pool in (s.pool, s.urgent_pool, s.replan_pool, s.io_pool, s.decode_pool, s.brake_pool):
        pool.shutdown(wait=False, cancel_futures=True)


def test_the_feed_is_the_active_plan_on_its_time_base_only_while_streaming(svc: Service) -> None:
    assert svc.sender.feed is None
    hold = hold_trajectory(np.array([1.0, 2.0, -3.0]), 0.0)
    svc.t_base = 100.0
    svc.active = hold
    assert svc.sender.feed is None  # not streaming yet
    svc.streaming = True
    assert svc.sender.feed == Feed(hold, 100.0)
    other = hold_trajectory(np.array([0.0, 0.0, -1.0]), 0.0)
    svc.active = other
    assert svc.sender.feed is not None and svc.sender.feed.trajectory is other
    svc.release_control()
    assert svc.sender.feed is None and not svc.streaming


def test_a_fresh_time_base_is_never_paired_with_the_previous_plan(svc: Service) -> None:
    log = FeedLog()
    svc.sender = log  # type: ignore[assignment]
    svc.take_control(np.array([1.0, 0.0, -2.0]), "first")
    first = svc.active
    t_first = svc.t_base
    time.sleep(0.01)
    svc.take_control(np.array([5.0, 0.0, -2.0]), "second")
    second, t_second = svc.active, svc.t_base
    assert first is not second and t_first != t_second
    seen = [(f.trajectory, f.t_base) for f in log.history if f is not None]
    assert any(traj is first and t == t_first for traj, t in seen)
    assert any(traj is second and t == t_second for traj, t in seen)
    assert all((traj is first) == (t == t_first) for traj, t in seen), seen


def _tick(now: float, feed: Feed | None, gap: float | None) -> Tick:
    sp = None if feed is None else Setpoint(np.zeros(3), np.zeros(3), np.zeros(3), 0.0)
    return Tick(now, now - 0.0002, now + 0.02, feed, sp, gap)


def test_ticks_feed_the_period_statistics_and_the_latency_report(svc: Service) -> None:
    events: list[tuple[str, dict[str, object]]] = []
    svc.event = lambda kind, message, **extra: events.append((kind, extra))  # type: ignore[method-assign]
    hold = hold_trajectory(np.zeros(3), 0.0)
    newer = hold_trajectory(np.ones(3), 0.0)
    svc.t_base = time.monotonic()
    svc.active = hold
    svc.streaming = True
    now = time.monotonic()
    svc._latency_mark = (now - 0.01, newer, "test")
    svc._on_tick(_tick(now, Feed(hold, svc.t_base), None))
    assert len(svc.periods) == 0 and svc.last_sp is not None
    assert svc._latency_mark is not None  # that tick flew the older plan: nothing to report yet
    svc.active = newer
    svc._on_tick(_tick(now + 0.02, Feed(newer, svc.t_base), 0.0201))
    assert list(svc.periods) == [0.0201] and svc.setpoint_gap_max == 0.0201
    assert svc._latency_mark is None and svc.setpoint_latency == pytest.approx(0.03)
    assert next(e for e in events if e[0] == "latency")[1]["immediate"] is False
    svc._on_tick(_tick(now + 0.04, None, None))
    assert svc.last_sp is None and len(svc.periods) == 1
