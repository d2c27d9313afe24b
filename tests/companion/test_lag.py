"""companion.lag, pure: the running least-squares lag recovers a known delay of a real planned
trajectory, takes nothing from samples at rest, stays within its cap, and does not swing."""

from __future__ import annotations

import numpy as np
import pytest

from companion.config import ConfigError, config_from_dict
from companion.lag import MEASURED_LAG, MIN_SPAN, LagEstimator, best_fit_lag, initial_lead
from companion.mission import start_mission
from companion.obstacles import Known
from companion.wire.messages import read
from planner_core import Trajectory, rest_jet


@pytest.fixture(scope="module")
def square() -> Trajectory:
    cfg = config_from_dict({})
    spec = read("mission", b'{"id": "m", "waypoints": [[8, 0, -2], [8, 8, -2], [0, 8, -2], [0, 0, -2]]}', cfg)
    out = start_mission(spec, rest_jet(np.array([0.0, 0.0, -2.0])), 0.0, Known(), cfg)  # type: ignore[arg-type]
    assert out.ok and out.route is not None
    return out.route.trajectory


def _fly(traj: Trajectory, delay: float, cap: float = 0.5, noise: float = 0.0) -> LagEstimator:
    rng = np.random.default_rng(3)
    est = LagEstimator(cap=cap)

    def stream_at(ts: np.ndarray) -> np.ndarray:
        return np.asarray(traj.evaluate(np.clip(ts, traj.t0, traj.t_end), 0))

    for t in np.arange(traj.t0, traj.t_end, 1 / 30):
        pos = traj.evaluate(max(t - delay, traj.t0), 0) + rng.normal(0.0, noise, 3)
        speed = float(np.linalg.norm(traj.evaluate(t, 1)))
        est.add(float(t), pos, speed, stream_at)
    return est


@pytest.mark.parametrize("delay", [0.06, 0.3])
def test_a_known_delay_is_recovered_and_held(square: Trajectory, delay: float) -> None:
    est = _fly(square, delay, noise=0.02)
    assert est.estimate is not None and est.estimate == pytest.approx(delay, abs=0.005)
    late = [e for t, e in est.history if t >= square.t_end - 3.0]
    assert np.ptp(late) <= 0.005  # settled: no swing over the last seconds
    # at rest (the plan does not move): nothing changes, the estimate is held
    before = est.estimate
    for t in np.arange(square.t_end, square.t_end + 5.0, 1 / 30):
        est.add(float(t), np.array([0.0, 0.0, -2.0]), 0.0, lambda ts: np.zeros((len(ts), 3)))
    assert est.estimate == before


def test_bounded_and_silent_until_enough_motion(square: Trajectory) -> None:
    est = _fly(square, 0.8, cap=0.5)
    assert est.estimate is not None and 0.0 <= est.estimate <= 0.5
    fresh = LagEstimator(cap=0.5)
    stream = lambda ts: np.asarray(square.evaluate(np.clip(ts, square.t0, square.t_end), 0))  # noqa: E731
    for t in np.arange(1.0, 1.0 + 0.8 * MIN_SPAN, 1 / 30):
        fresh.add(float(t), square.evaluate(t - 0.1, 0), 2.0, stream)
    assert fresh.estimate is None  # not from a moment of motion


def test_batch_fit_agrees(square: Trajectory) -> None:
    ts = np.arange(square.t0 + 1.0, square.t_end - 1.0, 0.02)
    measured = np.asarray(square.evaluate(ts - 0.123, 0))
    fit = best_fit_lag(ts, measured, lambda x: np.asarray(square.evaluate(x, 0)), cap=0.5, step=0.001)
    assert fit == pytest.approx(0.123, abs=0.0015)


def test_the_lead_starts_at_the_linked_autopilots_measured_lag() -> None:
    """Before the estimate has seen motion the auto lead is the lag measured on the autopilot
    (PX4 SIH ~0.33 s, ArduCopter ~0.06 s; ArduCopter's before one is found), or the seconds
    configured; never over lead_max."""
    assert initial_lead("autopilot", "px4", 0.5) == MEASURED_LAG["px4"] == 0.33
    assert initial_lead("autopilot", "ardupilot", 0.5) == MEASURED_LAG["ardupilot"] == 0.06
    assert initial_lead("autopilot", None, 0.5) == 0.06
    assert initial_lead("autopilot", "px4", 0.2) == 0.2
    assert initial_lead(0.1, "px4", 0.5) == 0.1
    assert config_from_dict({}).setpoints.lead_initial == 0.06
    assert config_from_dict({"setpoints": {"lead_initial": "autopilot"}}).setpoints.lead_initial == "autopilot"
    assert config_from_dict({"setpoints": {"lead_initial": 0.08}}).setpoints.lead_initial == 0.08
    for bad in ("fast", -0.1, True):
        with pytest.raises(ConfigError):
            config_from_dict({"setpoints": {"lead_initial": bad}})
