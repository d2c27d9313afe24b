"""A swapped-in plan is sent at once, off the periodic grid; a refused swap sends nothing."""

from __future__ import annotations

import time
from collections.abc import Iterator

import numpy as np
import pytest

from companion import route as rt
from companion.config import Config
from companion.service import Service
from companion.setpoints import Setpoint
from tests.companion.test_route import fly


@pytest.fixture
def svc() -> Iterator[Service]:
    s = Service(Config())
    sent: list[tuple[float, Setpoint]] = []
    s.link.send_setpoint = lambda sp: sent.append((time.monotonic(), sp))  # type: ignore[method-assign]
    s.sent = sent  # type: ignore[attr-defined]
    yield s
    for pool in (s.pool, s.urgent_pool, s.replan_pool, s.io_pool, s.decode_pool, s.brake_pool):
        pool.shutdown(wait=False, cancel_futures=True)


def flying(s: Service) -> rt.Route:
    r = fly([[0.0, 6.0, -1.5]], [0.0, 0.0, -1.5], t0=0.0)
    s.t_base = time.monotonic() - 1.0  # one second into the trajectory
    s.active = r.trajectory
    s.streaming = True
    return r


def test_a_swap_sends_one_setpoint_from_the_new_plan_at_once(svc: Service) -> None:
    r = flying(svc)
    now = svc.now_t()
    t_split = now + 0.3
    stop = rt.plan_stop(r.trajectory, [t_split], lambda: now, [], r.mission, r.mission.bounds, 0.05)
    assert stop.trajectory is not None
    new = rt.splice(r.trajectory, stop.trajectory)
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


def test_a_refused_swap_sends_nothing(svc: Service) -> None:
    r = flying(svc)
    now = svc.now_t()
    moved = rt.splice(r.trajectory, r.trajectory)  # same plan...
    shifted = type(moved)(moved.times, moved.control_points + 0.01, moved.corridors, moved.stats)  # ...moved 1 cm
    assert not svc.swap(shifted, now + 0.3, time.monotonic(), "test")
    assert svc.sent == [] and svc.active is r.trajectory  # type: ignore[attr-defined]


def test_nothing_is_sent_when_not_streaming(svc: Service) -> None:
    flying(svc)
    svc.streaming = False
    svc.send_now()
    assert svc.sent == []  # type: ignore[attr-defined]
