"""What Control hands the setpoint thread, and what it does with each tick."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest

from companion.control import Control
from companion.setpoints import Feed, Setpoint, Tick, YawPolicy
from planner_core import hold as hold_trajectory


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


class Target:
    feed: Feed | None = None


def control(target: object | None = None, on_latency: object = None) -> Control:
    kw = {} if on_latency is None else {"on_latency": on_latency}
    return Control(target or Target(), lambda sp: None, YawPolicy("fixed", 0.0, 0.5), 50.0, **kw)  # type: ignore[arg-type]


@pytest.fixture
def ctl() -> Iterator[Control]:
    yield control()


def test_the_feed_is_the_active_plan_on_its_time_base_only_while_streaming(ctl: Control) -> None:
    assert ctl.target.feed is None
    hold = hold_trajectory(np.array([1.0, 2.0, -3.0]), 0.0)
    ctl._set(hold, 100.0, False)
    assert ctl.target.feed is None  # not streaming yet
    ctl._set(hold, 100.0, True)
    assert ctl.target.feed == Feed(hold, 100.0)
    other = hold_trajectory(np.array([0.0, 0.0, -1.0]), 0.0)
    ctl._set(other, 100.0, True)
    assert ctl.target.feed is not None and ctl.target.feed.trajectory is other
    ctl.release()
    assert ctl.target.feed is None and not ctl.streaming


def test_a_fresh_time_base_is_never_paired_with_the_previous_plan() -> None:
    log = FeedLog()
    svc = control(log)
    svc.take(np.array([1.0, 0.0, -2.0]), 0.0, "first")
    first = svc.active
    t_first = svc.t_base
    time.sleep(0.01)
    svc.take(np.array([5.0, 0.0, -2.0]), 0.0, "second")
    second, t_second = svc.active, svc.t_base
    assert first is not second and t_first != t_second
    seen = [(f.trajectory, f.t_base) for f in log.history if f is not None]
    assert any(traj is first and t == t_first for traj, t in seen)
    assert any(traj is second and t == t_second for traj, t in seen)
    assert all((traj is first) == (t == t_first) for traj, t in seen), seen


def _tick(now: float, feed: Feed | None, gap: float | None) -> Tick:
    sp = None if feed is None else Setpoint(np.zeros(3), np.zeros(3), np.zeros(3), 0.0)
    return Tick(now, now - 0.0002, now + 0.02, feed, sp, gap)


def test_ticks_feed_the_period_statistics_and_the_latency_report() -> None:
    events: list[tuple[str, dict[str, object]]] = []
    svc = control(on_latency=lambda what, s, immediate, mono: events.append(("latency", {"immediate": immediate})))
    hold = hold_trajectory(np.zeros(3), 0.0)
    newer = hold_trajectory(np.ones(3), 0.0)
    t_base = time.monotonic()
    svc._set(hold, t_base, True)
    now = time.monotonic()
    svc._latency_mark = (now - 0.01, newer, "test")
    svc.on_tick(_tick(now, Feed(hold, t_base), None))
    assert len(svc.periods) == 0 and svc.last_sp is not None
    assert svc._latency_mark is not None  # that tick flew the older plan: nothing to report yet
    svc._set(newer, t_base, True)
    svc.on_tick(_tick(now + 0.02, Feed(newer, t_base), 0.0201))
    assert list(svc.periods) == [0.0201] and svc.setpoint_gap_max == 0.0201
    assert svc._latency_mark is None and svc.setpoint_latency == pytest.approx(0.03)
    assert next(e for e in events if e[0] == "latency")[1]["immediate"] is False
    svc.on_tick(_tick(now + 0.04, None, None))
    assert svc.last_sp is None and len(svc.periods) == 1
