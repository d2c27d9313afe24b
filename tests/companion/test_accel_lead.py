"""Setpoints aimed beyond the plan by accel_lead x its (low-passed) acceleration.

ArduCopter trails a plan by about k F beyond its time lag, F the plan's acceleration low-passed
over a second or so (measured on ArduCopter 4.6-dev SITL: docs/autopilot-limits.md), so the
setpoints aim at p + k F. They must stay one coherent target (velocity the derivative of the
position, acceleration that of the velocity), be the plan's own jet when the option is off, and
say exactly what the demo's analysis reconstructs from the plan (demo.report.aimed).
"""

from __future__ import annotations

import itertools
import socket
import threading
import time

import numpy as np
import pytest

from companion.lag import PX4_SIH_AIM_HORIZONTAL
from companion.sendproc import Encoding, SetpointProcess
from companion.setpoints import Feed, Tick, YawPolicy, filtered_accel, sample
from demo.report import aimed
from planner_core import Trajectory, sampler

YAW = YawPolicy("fixed", 0.0, 0.3)


def _curve() -> Trajectory:
    """One degree-9 piece from rest to rest (velocity, acceleration and jerk 0 at both ends)
    that swings on both horizontal axes: an S over ~10 m in 8 s."""
    ctrl = np.zeros((10, 3))
    ctrl[4] = [4.0, 6.0, -0.5]
    ctrl[5] = [8.0, -3.0, 0.5]
    ctrl[6:] = [10.0, 2.0, 0.0]
    return Trajectory(np.array([0.0, 8.0]), ctrl[None])


def _constant_acceleration(acc: np.ndarray, seconds: float = 10.0) -> Trajectory:
    """p(t) = acc t^2 / 2 as one degree-9 Bezier piece."""
    t = np.linspace(0.0, seconds, 10)
    # the Bezier control points of a quadratic raised to degree 9
    ctrl = np.zeros((10, 3))
    for i in range(10):
        ctrl[i] = acc * seconds**2 * (i * (i - 1)) / (9 * 8) / 2
    del t
    return Trajectory(np.array([0.0, seconds]), ctrl[None])


def test_off_is_the_plans_own_jet() -> None:
    traj = _curve()
    for t in np.linspace(-1.0, 14.0, 31):
        sp = sample(traj, float(t), YAW)
        jet = sampler(traj).jet3(float(t))
        assert np.array_equal(sp.position, jet[0]) and np.array_equal(sp.velocity, jet[1])
        assert np.array_equal(sp.acceleration, jet[2])


@pytest.mark.parametrize("tc", [0.0, 0.4, 1.0])
def test_the_aimed_target_is_coherent(tc: float) -> None:
    """Velocity is the derivative of the aimed position, acceleration that of the velocity, at
    every time (the autopilot forward-predicts its target with them between setpoints)."""
    traj, k, dt = _curve(), 0.09, 0.002
    ts = np.arange(0.0, traj.t_end + 4.0 * max(tc, 0.1), dt)
    sps = [sample(traj, float(t), YAW, k, tc) for t in ts]
    p = np.array([s.position for s in sps])
    v = np.array([s.velocity for s in sps])
    a = np.array([s.acceleration for s in sps])
    scale_v, scale_a = np.abs(v).max(), np.abs(a).max()
    # (at the plan's end its snap stops at once: the aimed acceleration k s steps there)
    inner = np.abs(ts - traj.t_end) > 2 * dt
    inner[:2] = inner[-2:] = False
    assert np.abs(np.gradient(p, dt, axis=0) - v)[inner].max() < 2e-3 * scale_v
    # the filter's 40 ms midpoint sum leaves a ripple in F's second derivative: 1 % of the peak
    assert np.abs(np.gradient(v, dt, axis=0) - a)[inner].max() < 1e-2 * scale_a
    offset = p - traj.evaluate(np.clip(ts, traj.t0, traj.t_end))
    assert np.abs(offset).max() > 0.02  # it aims beyond the plan at all
    assert np.abs(offset).max() <= k * np.abs(traj.evaluate(np.linspace(0, traj.t_end, 2001), 2)).max() * 1.01


def test_the_filter_passes_a_constant_acceleration_and_forgets_the_plan_past_its_end() -> None:
    acc = np.array([0.6, -0.3, 0.1])
    traj = _constant_acceleration(acc)
    for t in (0.0, 0.5, 3.0, 9.9):
        assert np.allclose(filtered_accel(traj, t, 1.0), acc, atol=1e-9)
    # past the end the plan is at rest: F decays with the time constant
    late = [np.linalg.norm(filtered_accel(traj, traj.t_end + s, 1.0)) for s in (0.5, 1.0, 2.0, 3.0)]
    assert all(b < a for a, b in itertools.pairwise(late))
    assert np.allclose(late[1] / np.linalg.norm(acc), np.exp(-1.0), rtol=0.05)


@pytest.mark.parametrize("tc", [0.0, 1.0])
def test_the_analysis_reconstructs_the_aim_from_the_plan(tc: float) -> None:
    """demo.report.aimed (what the demo matches the logged setpoints against) is the aim."""
    traj, k = _curve(), 0.09
    ts = np.linspace(0.0, traj.t_end + 2.0, 400)
    want = np.array([sample(traj, float(t), YAW, k, tc).position for t in ts])
    got = aimed([traj], [-np.inf], ts, k, tc)
    assert np.abs(got - want).max() < 1e-4


@pytest.mark.parametrize("aim", [(0.09, 1.0, ()), (0.0, 0.0, PX4_SIH_AIM_HORIZONTAL)])
def test_the_setpoint_process_aims_as_the_service_set_before_it_ran(
        aim: tuple[float, float, tuple[tuple[float, float], ...]]) -> None:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    ticks: list[Tick] = []
    lock = threading.Lock()

    def on_tick(tick: Tick) -> None:
        with lock:
            ticks.append(tick)

    sender = SetpointProcess(50.0, lambda: (sock.fileno(), True, Encoding(255, 191, 1, 1, None, time.monotonic())),
                             YawPolicy("fixed", 0.0, 0.3), on_tick, lambda exc: None)
    # as the service does at construction, before the process runs
    sender.accel_lead, sender.accel_lead_tc, sender.aim_horizontal = aim
    sender.start()
    traj = _curve()
    try:
        t_base = time.monotonic()
        sender.feed = Feed(traj, t_base)
        time.sleep(0.5)
        with lock:
            got = [t for t in ticks if t.setpoint is not None]
        assert len(got) >= 10
        for t in got:
            want = sample(traj, t.now - t_base, YAW, *aim)
            assert np.allclose(t.setpoint.position, want.position, atol=1e-9)
            assert np.allclose(t.setpoint.velocity, want.velocity, atol=1e-9)
    finally:
        sender.stop()
        sock.close()


H_TERMS = PX4_SIH_AIM_HORIZONTAL


def test_the_horizontal_terms_aim_in_the_plane_only_and_coherently() -> None:
    """Each horizontal term adds k F of its own time constant to x and y only; the target stays
    coherent, and with the 3-D term as well the two add up."""
    traj, dt = _curve(), 0.002
    ts = np.arange(0.0, traj.t_end + 16.0, dt)
    plain = np.array([sample(traj, float(t), YAW).position for t in ts])
    sps = [sample(traj, float(t), YAW, 0.0, 0.0, H_TERMS) for t in ts]
    p = np.array([s.position for s in sps])
    v = np.array([s.velocity for s in sps])
    a = np.array([s.acceleration for s in sps])
    assert np.array_equal(p[:, 2], plain[:, 2])  # z is the plan's
    want = sum(k * np.array([filtered_accel(traj, float(t), tc) for t in ts[::50]]) for k, tc in H_TERMS)
    assert np.allclose(p[::50, :2] - plain[::50, :2], np.asarray(want)[:, :2], atol=1e-12)
    inner = np.abs(ts - traj.t_end) > 2 * dt
    inner[:2] = inner[-2:] = False
    assert np.abs(np.gradient(p, dt, axis=0) - v)[inner].max() < 2e-3 * np.abs(v).max()
    assert np.abs(np.gradient(v, dt, axis=0) - a)[inner].max() < 1e-2 * np.abs(a).max()
    # long after the end the aim has settled on the plan's end point
    assert np.allclose(p[-1], plain[-1], atol=0.05)
    both = sample(traj, 5.0, YAW, 0.09, 1.0, H_TERMS).position
    one = sample(traj, 5.0, YAW, 0.09, 1.0).position
    assert np.allclose(both - one, sample(traj, 5.0, YAW, 0.0, 0.0, H_TERMS).position - plain[2500], atol=1e-12)


def test_the_analysis_reconstructs_the_horizontal_aim() -> None:
    traj = _curve()
    ts = np.linspace(0.0, traj.t_end + 6.0, 400)
    want = np.array([sample(traj, float(t), YAW, 0.09, 1.0, H_TERMS).position for t in ts])
    got = aimed([traj], [-np.inf], ts, 0.09, 1.0, H_TERMS)
    assert np.abs(got - want).max() < 1e-4


def test_the_horizontal_aim_option() -> None:
    from companion.config import ConfigError, config_from_dict
    from companion.lag import initial_aim_horizontal

    assert config_from_dict({}).setpoints.aim_horizontal == "autopilot"
    assert initial_aim_horizontal("autopilot", "px4") == initial_aim_horizontal("autopilot", "ardupilot") == ()
    cfg = config_from_dict({"setpoints": {"aim_horizontal": [list(t) for t in PX4_SIH_AIM_HORIZONTAL]}})
    assert cfg.setpoints.aim_horizontal == PX4_SIH_AIM_HORIZONTAL
    assert initial_aim_horizontal(cfg.setpoints.aim_horizontal, "px4") == PX4_SIH_AIM_HORIZONTAL
    for bad, where in (([[1.0, 0.0]], r"aim_horizontal\[0\]"), ([[11.0, 1.0]], r"aim_horizontal\[0\]"),
                       ([[1.0, 1.0]] * 5, "aim_horizontal"), ("more", "aim_horizontal"),
                       ([[1.0, 1.0], [True, 1.0]], r"aim_horizontal\[1\]")):
        with pytest.raises(ConfigError, match=where):
            config_from_dict({"setpoints": {"aim_horizontal": bad}})
