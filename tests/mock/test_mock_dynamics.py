"""Vehicle model: step response, feed-forward tracking, limits and ground contact."""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import pytest

from sitl_mock.vehicle import RESPONSES, G, Target, Vehicle

DT = 1.0 / 250.0


def run_step(axis: int, step: float, seconds: float = 15.0) -> np.ndarray:
    v = Vehicle()
    v.reset(np.array([0.0, 0.0, -10.0]))
    target = Target.hold(np.array([0.0, 0.0, -10.0]), 0.0)
    target.pos[axis] += step
    trace = []
    for _ in range(int(seconds / DT)):
        v.step(DT, target, True, np.zeros(3))
        trace.append(v.state.pos[axis])
    return np.asarray(trace) - target.pos[axis]


@pytest.mark.parametrize(("axis", "step"), [(0, 1.0), (0, 5.0), (1, -20.0), (2, -3.0), (2, 4.0)])
def test_position_step_settles_without_overshoot(axis: int, step: float) -> None:
    err = run_step(axis, step)
    overshoot = float(np.max(err * np.sign(step)))  # past the target, in the step direction
    assert overshoot <= 0.10 * abs(step)
    assert abs(err[-1]) < 0.01 * abs(step)


def _curve(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A figure of eight with a vertical wave; smooth, with matching pos/vel/acc."""
    w = 0.7
    p = np.array([3 * math.sin(w * t), 1.5 * math.sin(2 * w * t), -5 + 0.5 * math.sin(0.5 * t)])
    v = np.array([3 * w * math.cos(w * t), 3 * w * math.cos(2 * w * t), 0.25 * math.cos(0.5 * t)])
    a = np.array([-3 * w * w * math.sin(w * t), -6 * w * w * math.sin(2 * w * t),
                  -0.125 * math.sin(0.5 * t)])
    return p, v, a


def test_feed_forward_trajectory_tracked_within_5cm_rms() -> None:
    veh = Vehicle(RESPONSES["ideal"])
    p0, v0, a0 = _curve(0.0)
    veh.reset(p0)
    veh.state.vel = v0.copy()
    veh.state.acc = a0.copy()
    veh.state.on_ground = False
    errors = []
    for k in range(int(20.0 / DT)):
        p, v, a = _curve(k * DT)
        veh.step(DT, Target(p, v, a, math.nan, math.nan), True, np.zeros(3))
        errors.append(np.linalg.norm(veh.state.pos - _curve((k + 1) * DT)[0]))
    rms = math.sqrt(float(np.mean(np.square(errors))))
    assert rms <= 0.05


def test_feed_forward_matters() -> None:
    """Without feed-forward the same curve is tracked much worse (the test above is not vacuous)."""
    veh = Vehicle()
    veh.reset(_curve(0.0)[0])
    errors = []
    for k in range(int(20.0 / DT)):
        p, _, _ = _curve(k * DT)
        veh.step(DT, Target.hold(p, 0.0), True, np.zeros(3))
        errors.append(np.linalg.norm(veh.state.pos - _curve((k + 1) * DT)[0]))
    assert math.sqrt(float(np.mean(np.square(errors)))) > 0.2


def test_tilt_climb_and_descent_limits() -> None:
    veh = Vehicle()
    veh.reset(np.array([0.0, 0.0, -50.0]))
    far = Target.hold(np.array([500.0, 0.0, -150.0]), 0.0)
    max_acc_xy, min_vz = 0.0, 0.0
    for _ in range(int(10 / DT)):
        veh.step(DT, far, True, np.zeros(3))
        max_acc_xy = max(max_acc_xy, float(np.hypot(*veh.state.acc[:2])))
        min_vz = min(min_vz, float(veh.state.vel[2]))
    assert max_acc_xy <= G * math.tan(math.radians(veh.params.max_tilt_deg)) + 1e-9
    assert min_vz >= -veh.params.max_climb - 0.05
    down = Target.hold(np.array([0.0, 0.0, 0.0]), 0.0)
    max_vz = 0.0
    for _ in range(int(10 / DT)):
        veh.step(DT, down, True, np.zeros(3))
        max_vz = max(max_vz, float(veh.state.vel[2]))
    assert max_vz <= veh.params.max_descent + 0.05


def test_ground_stops_descent_and_reports_landed() -> None:
    veh = Vehicle()
    veh.reset(np.array([0.0, 0.0, -2.0]))
    below = Target.hold(np.array([0.0, 0.0, 5.0]), 0.0)  # a target underground
    for _ in range(int(5 / DT)):
        veh.step(DT, below, True, np.zeros(3))
        assert veh.state.pos[2] <= 0.0
    assert veh.state.on_ground


def test_disarmed_vehicle_falls_and_rests_on_ground() -> None:
    veh = Vehicle()
    veh.reset(np.array([0.0, 0.0, -1.0]))
    for _ in range(int(2 / DT)):
        veh.step(DT, None, False, np.zeros(3))
    assert veh.state.pos[2] == 0.0 and veh.state.on_ground


def test_wind_pushes_a_hovering_vehicle() -> None:
    veh = Vehicle()
    veh.reset(np.array([0.0, 0.0, -5.0]))
    hold = Target.hold(np.array([0.0, 0.0, -5.0]), 0.0)
    for _ in range(int(10 / DT)):
        veh.step(DT, hold, True, np.array([5.0, 0.0, 0.0]))
    assert veh.state.pos[0] > 0.05 and veh.state.pos[2] == pytest.approx(-5.0, abs=1e-3)


def test_attitude_follows_thrust_direction() -> None:
    veh = Vehicle()
    veh.state.acc = np.array([G, 0.0, 0.0])
    roll, pitch, _ = veh.attitude()
    assert pitch == pytest.approx(-math.pi / 4) and roll == pytest.approx(0.0)



def _circle(t: float, speed: float = 3.0, r: float = 6.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A level circle at `speed` with a slow vertical wave: a curved path as the demo flies."""
    w = speed / r
    p = np.array([r * math.sin(w * t), r * (1 - math.cos(w * t)), -5 + 0.5 * math.sin(0.3 * t)])
    v = np.array([speed * math.cos(w * t), speed * math.sin(w * t), 0.15 * math.cos(0.3 * t)])
    a = np.array([-speed * w * math.sin(w * t), speed * w * math.cos(w * t), -0.045 * math.sin(0.3 * t)])
    return p, v, a


Curve = Callable[[float], tuple[np.ndarray, np.ndarray, np.ndarray]]


def _track(response: str, curve: Curve, seconds: float = 20.0, lead: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Fly `curve` with full feed-forward setpoints at 50 Hz (sampled `lead` ahead); flown and planned."""
    veh = Vehicle(RESPONSES[response])
    p0, v0, a0 = curve(0.0)
    veh.reset(p0)
    veh.state.vel, veh.state.acc, veh.state.on_ground = v0.copy(), a0.copy(), False
    flown, planned = [], []
    target = Target(p0, v0, a0, math.nan, math.nan)
    for k in range(int(seconds / DT)):
        t = k * DT
        if k % 5 == 0:  # 50 Hz setpoints
            target = Target(*curve(t + lead), math.nan, math.nan)
        veh.step(DT, target, True, np.zeros(3))
        flown.append(veh.state.pos.copy())
        planned.append(curve(t + DT)[0])
    return np.asarray(flown), np.asarray(planned)


def _rms(flown: np.ndarray, planned: np.ndarray) -> float:
    return math.sqrt(float(np.mean(np.sum((flown[500:] - planned[500:]) ** 2, axis=1))))


def _lag(flown: np.ndarray, curve: Curve) -> float:
    """The effective time lag of a flown curve: the delay that best explains it."""
    ts = np.arange(len(flown)) * DT + DT
    best = (math.inf, 0.0)
    for d in np.arange(0.0, 0.2, 0.002):
        plan = np.array([curve(max(0.0, t - d))[0] for t in ts[500::10]])
        rms = math.sqrt(float(np.mean(np.sum((flown[500::10] - plan) ** 2, axis=1))))
        best = min(best, (rms, float(d)))
    return best[1]


@pytest.mark.parametrize("speed", [3.0, 3.4])
def test_calibrated_response_lags_as_arducopter_does(speed: float) -> None:
    """The default response: an effective lag of 55-75 ms on a curved path at up to 3.4 m/s
    (issue 11's ArduCopter SITL figures: 57 and 74 ms), an error the ideal one does not have,
    and sampling setpoints ahead by the lag takes much of it away."""
    assert Vehicle().params == RESPONSES["calibrated"]  # the default

    def curve(t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return _circle(t, speed)

    flown, planned = _track("calibrated", curve)
    lag = _lag(flown, curve)
    assert 0.055 <= lag <= 0.075, lag
    rms = _rms(flown, planned)
    assert rms > 5 * _rms(*_track("ideal", curve))
    assert _rms(*_track("calibrated", curve, lead=lag)) < 0.7 * rms
