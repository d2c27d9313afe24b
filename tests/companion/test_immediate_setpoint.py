"""A swapped-in plan is sent at once, off the periodic grid; a refused swap sends nothing."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest

from companion.braking import plan_stop
from companion.control import Control
from companion.route import Route
from companion.setpoints import Feed, Setpoint, YawPolicy
from planner_core import splice
from tests.companion.test_route import fly


class Target:
    feed: Feed | None = None


@pytest.fixture
def svc() -> Iterator[Control]:
    sent: list[tuple[float, Setpoint]] = []
    s = Control(Target(), lambda sp: sent.append((time.monotonic(), sp)), YawPolicy("fixed", 0.0, 0.5), 50.0)
    s.sent = sent  # type: ignore[attr-defined]
    yield s


def flying(s: Control) -> Route:
    r = fly([[0.0, 6.0, -1.5]], [0.0, 0.0, -1.5], t0=0.0)
    s._set(r.trajectory, time.monotonic() - 1.0, True)  # one second into the trajectory
    return r


def test_a_swap_sends_one_setpoint_from_the_new_plan_at_once(svc: Control) -> None:
    r = flying(svc)
    now = svc.now()
    t_split = now + 0.3
    stop = plan_stop(r.trajectory, [t_split], lambda: now, [], r.mission, r.mission.bounds, 0.05)
    assert stop.trajectory is not None
    new = splice(r.trajectory, stop.trajectory)
    arrived = time.monotonic() - 0.004
    assert svc.swap(new, stop.start, arrived, "test")
    sent = svc.sent  # type: ignore[attr-defined]
    assert len(sent) == 1
    t_send, sp = sent[0]
    # sampled from the new plan between the message and the send (the leg runs along +y)
    assert svc.t_base is not None
    lo, hi = new.evaluate(np.array([arrived - svc.t_base, t_send - svc.t_base]))[:, 1]
    assert lo - 1e-12 <= sp.position[1] <= hi + 1e-12 and hi > lo
    # the latency is measured at that send, and the periodic statistics did not see it
    assert svc.setpoint_latency is not None and 0.004 <= svc.setpoint_latency <= t_send - arrived + 1e-9
    assert svc._latency_mark is None and svc.last_sp is None and len(svc.periods) == 0


def test_a_refused_swap_sends_nothing(svc: Control) -> None:
    r = flying(svc)
    now = svc.now()
    moved = splice(r.trajectory, r.trajectory)  # same plan...
    shifted = type(moved)(moved.times, moved.control_points + 0.01, moved.corridors, moved.stats)  # ...moved 1 cm
    assert not svc.swap(shifted, now + 0.3, time.monotonic(), "test")
    assert svc.sent == [] and svc.active is r.trajectory  # type: ignore[attr-defined]


def test_nothing_is_sent_when_not_streaming(svc: Control) -> None:
    flying(svc)
    svc.pause()
    svc.send_now()
    assert svc.sent == []  # type: ignore[attr-defined]
