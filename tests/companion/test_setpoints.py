from __future__ import annotations

import asyncio
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from companion.setpoints import DeadlineScheduler, YawPolicy, sample, sleep_until
from planner_core import hold as hold_trajectory


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


# -- the fast sampler -----------------------------------------------------------------------


def test_sampler_agrees_with_trajectory_jet_and_is_at_rest_past_the_end() -> None:
    from planner_core import Sampler
    from tests.companion.test_route import fly

    traj = fly([[3.0, 0.0, -1.5], [3.0, 3.0, -2.0], [0.0, 3.0, -1.5]], [0.0, 0.0, -1.5], t0=2.0).trajectory
    s = Sampler(traj)
    scale = np.max(np.abs(np.stack([traj.jet(t) for t in np.linspace(traj.t0, traj.t_end, 50)])), axis=(0, 2))
    # inside, on every boundary, and clamped outside the span
    ts = np.concatenate([np.linspace(traj.t0 - 1.0, traj.t_end + 1.0, 997), traj.times])
    for t in ts:
        ref = traj.jet(t)
        got = s.jet(float(t))
        assert np.all(np.abs(got - ref) <= 1e-12 * (1.0 + scale[:, None])), (t, got - ref)
        three = s.jet3(float(t))
        assert np.all(np.abs(three[0] - got[0]) <= 1e-12 * (1.0 + scale[0]))
        if t >= traj.t_end:
            assert not three[1:].any()  # exactly at rest past the end
        else:
            assert np.all(np.abs(three[1:] - got[1:3]) <= 1e-12 * (1.0 + scale[1:3, None]))
    # many times at once (the aim's low-passed acceleration), every order, across segments
    for order in range(5):
        ref = traj.evaluate(np.clip(ts, traj.t0, traj.t_end), order)
        got = s.many(ts, order)
        assert got.shape == ref.shape
        assert np.all(np.abs(got - ref) <= 1e-12 * (1.0 + scale[order])), order
        inner = ts[(ts > traj.times[1]) & (ts < traj.times[2])]  # within one segment: the one-product path
        assert np.all(np.abs(s.many(inner, order) - traj.evaluate(inner, order)) <= 1e-12 * (1.0 + scale[order]))
    yaw = YawPolicy("hold", 0.0, 0.3)
    sp = sample(traj, 3.0, yaw)
    assert np.array_equal(sp.position, s.jet3(3.0)[0]) and np.array_equal(sp.acceleration, s.jet3(3.0)[2])


# -- the setpoint thread ------------------------------------------------------------------------


class _Recorder:
    def __init__(self) -> None:
        self.sent: list[tuple[float, object]] = []
        self.ticks: list[object] = []
        self.failures: list[BaseException] = []
        self.ready = threading.Event()

    def send(self, sp: object) -> None:
        self.sent.append((time.monotonic(), sp))

    def on_tick(self, tick: object) -> None:
        self.ticks.append(tick)
        if len(self.ticks) >= 20:
            self.ready.set()


def test_sender_sends_on_the_absolute_grid_and_only_with_a_feed() -> None:
    from companion.setpoints import Feed, SetpointSender, Tick

    rec = _Recorder()
    hold = hold_trajectory(np.array([1.0, -2.0, -3.0]), 0.0)
    sender = SetpointSender(100.0, rec.send, YawPolicy("fixed", 0.25, 0.3), rec.on_tick, rec.failures.append)
    sender.start()
    try:
        assert rec.ready.wait(10.0)
        sender.feed = Feed(hold, time.monotonic())
        n = len(rec.ticks)
        while len(rec.ticks) < n + 20:
            time.sleep(0.01)
    finally:
        sender.stop()
    ticks: list[Tick] = list(rec.ticks)  # type: ignore[arg-type]
    t0 = ticks[0].deadline
    ks = [round((tk.deadline - t0) * 100.0) for tk in ticks]
    assert ks == sorted(set(ks))  # one tick per deadline, in order, never two on one
    for tk in ticks:
        assert tk.deadline == pytest.approx(t0 + round((tk.deadline - t0) * 100.0) / 100.0, abs=1e-9)
        assert tk.now >= tk.deadline  # never early
        assert tk.next_deadline > tk.deadline
    fed = [tk for tk in ticks if tk.feed is not None]
    assert fed and len(rec.sent) == len(fed) and not rec.failures
    assert all(tk.setpoint is not None and np.allclose(tk.setpoint.position, [1.0, -2.0, -3.0], rtol=0, atol=1e-12)
               for tk in fed)
    assert all(sp.yaw == 0.25 for _, sp in rec.sent)  # type: ignore[attr-defined]
    # periods are measured between periodic sends only, from the second one on
    assert fed[0].gap is None and all(tk.gap is not None and tk.gap > 0 for tk in fed[1:])
    assert all(tk.setpoint is None for tk in ticks if tk.feed is None)


def test_sender_reports_a_crash_and_stops() -> None:
    from companion.setpoints import Feed, SetpointSender

    rec = _Recorder()

    def broken(sp: object) -> None:
        raise RuntimeError("boom")

    sender = SetpointSender(200.0, broken, YawPolicy("hold", 0.0, 0.3), rec.on_tick, rec.failures.append)
    sender.feed = Feed(hold_trajectory(np.zeros(3), 0.0), time.monotonic())
    sender.start()
    deadline = time.monotonic() + 10.0
    while not rec.failures and time.monotonic() < deadline:
        time.sleep(0.01)
    sender.stop()
    assert len(rec.failures) == 1 and "boom" in repr(rec.failures[0])


def test_sender_survives_a_refused_send() -> None:
    from companion.setpoints import Feed, SetpointSender

    rec = _Recorder()
    calls = []

    def refusing(sp: object) -> None:
        calls.append(sp)
        raise OSError("network unreachable")

    sender = SetpointSender(200.0, refusing, YawPolicy("hold", 0.0, 0.3), rec.on_tick, rec.failures.append)
    sender.feed = Feed(hold_trajectory(np.zeros(3), 0.0), time.monotonic())
    sender.start()
    try:
        assert rec.ready.wait(10.0)
    finally:
        sender.stop()
    assert not rec.failures and len(calls) >= 20
    assert all(isinstance(tk.error, OSError) for tk in rec.ticks)  # type: ignore[attr-defined]


@pytest.mark.skipif(not Path("/proc/self/task").is_dir(), reason="Linux only")
def test_sender_thread_is_named_and_normal_unless_asked() -> None:
    from companion.setpoints import SetpointSender

    rec = _Recorder()
    sender = SetpointSender(100.0, rec.send, YawPolicy("hold", 0.0, 0.3), rec.on_tick, rec.failures.append)
    sender.start()
    try:
        assert rec.ready.wait(10.0)
        assert sender.native_id is not None
        comm = Path(f"/proc/self/task/{sender.native_id}/comm").read_text().strip()
    finally:
        sender.stop()
    assert comm == "setpoints"
    assert sender.scheduling == "normal"
