"""The mock shapes targets with the autopilot's own limits, read live from its parameters
(issue 26 point 3), over real MAVLink/UDP with pymavlink as the client.

ArduCopter GUIDED: WPNAV_* / PSC_JERK_* through AC_PosControl's jerk-limited shaping
(sitl_mock.shaping). Measured on ArduCopter SITL (autopilot-facts.md): a 14.1 m diagonal
with |v| 5.46 m/s and |a| 4.47 m/s^2 was flown up to 6.85 m/s and overshot by 3.36 m; a
plan within the limits flew at 0.110 m RMS. PX4: MPC_XY_VEL_MAX / MPC_Z_VEL_MAX_* bound the
offboard velocity setpoint.
"""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from mockkit import CUSTOM, POS_ONLY, Client, Streamer, records, wait_for
from pymavlink.dialects.v20 import common as mav

GUIDED = 4
ACCEPTED = mav.MAV_RESULT_ACCEPTED
PVA = 0b0000_1100_0000_0000
VEL_ONLY = 0b0000_1101_1100_0111
ALT = 6.0

AP_DEFAULTS = {"WPNAV_SPEED": 1000.0, "WPNAV_ACCEL": 250.0, "WPNAV_SPEED_UP": 250.0, "WPNAV_SPEED_DN": 150.0,
               "WPNAV_ACCEL_Z": 100.0, "PSC_JERK_XY": 5.0, "PSC_JERK_Z": 5.0}
PX4_DEFAULTS = {"MPC_XY_VEL_MAX": 12.0, "MPC_Z_VEL_MAX_UP": 3.0, "MPC_Z_VEL_MAX_DN": 1.5, "MPC_ACC_HOR_MAX": 5.0,
                "MPC_ACC_UP_MAX": 4.0, "MPC_ACC_DOWN_MAX": 3.0, "MPC_TILTMAX_AIR": 45.0, "MPC_JERK_MAX": 8.0}


def read_param(c: Client, name: str) -> float:
    c.drain()
    c.mav.param_request_read_send(1, 1, name.encode(), -1)
    msg = c.wait("PARAM_VALUE", 3, lambda m: m.param_id == name)
    assert msg is not None, f"no PARAM_VALUE for {name}"
    return float(msg.param_value)


def set_param(c: Client, name: str, value: float) -> float:
    c.drain()
    c.mav.param_set_send(1, 1, name.encode(), value, mav.MAV_PARAM_TYPE_REAL32)
    msg = c.wait("PARAM_VALUE", 3, lambda m: m.param_id == name)
    assert msg is not None, f"PARAM_SET {name} not answered"
    return float(msg.param_value)


def scurve(d: float, v: float, a: float, j: float, dt: float = 0.002) -> tuple[float, np.ndarray]:
    """A rest-to-rest jerk-limited profile over d: rows (t, p, v, a)."""
    tj = a / j
    ta = v / a - tj
    t_acc = 2 * tj + ta
    tc = (d - v * t_acc) / v
    assert ta >= 0 and tc >= 0
    phases = [(tj, j), (ta, 0.0), (tj, -j), (tc, 0.0), (tj, -j), (ta, 0.0), (tj, j)]
    total = sum(p[0] for p in phases)
    rows, p, vel, acc, t = [], 0.0, 0.0, 0.0, 0.0
    bounds = np.cumsum([p[0] for p in phases])
    while t <= total + dt:
        rows.append((t, p, vel, acc))
        jerk = next((jj for end, (_, jj) in zip(bounds, phases, strict=True) if t < end), 0.0)
        p += vel * dt + acc * dt * dt / 2 + jerk * dt**3 / 6
        vel += acc * dt + jerk * dt * dt / 2
        acc += jerk * dt
        t += dt
    return total, np.array(rows)


def fly_diagonal(mock, c, v: float, a: float, j: float, d: float = 10.0):  # type: ignore[no-untyped-def]
    """Stream a diagonal (d, d) pos+vel+acc plan at 50 Hz of simulated time; the flown states
    after it started and the plan, as (t, p) along the diagonal."""
    total, plan = scurve(d, v, a, j)
    t0 = mock.snapshot()["t"]
    while (t := mock.snapshot()["t"] - t0) < total + 6.0:
        i = min(int(t / 0.002), len(plan) - 1)
        _, p, vel, acc = plan[i]
        c.setpoint(x=p, y=p, z=-ALT, mask=PVA, vel=(vel, vel, 0.0), acc=(acc, acc, 0.0))
        time.sleep(0.02 / mock.config.speed)
    states = [r for r in records(mock, "state") if r["t"] >= t0]
    ts = np.array([r["t"] - t0 for r in states])
    pos = np.array([r["pos"] for r in states])
    vel = np.array([r["vel"] for r in states])
    planned = np.interp(ts, plan[:, 0], plan[:, 1])
    err = np.hypot(pos[:, 0] - planned, pos[:, 1] - planned)
    along = (pos[:, 0] + pos[:, 1]) / math.sqrt(2)
    return {
        "overshoot": float(along.max() - d * math.sqrt(2)),
        "peak_speed": float(np.hypot(vel[:, 0], vel[:, 1]).max()),
        "rms": float(np.sqrt(np.mean(err[ts <= total] ** 2))),
        "plan_speed": float(plan[:, 2].max() * math.sqrt(2)),
        "plan_acc": float(np.abs(plan[:, 3]).max() * math.sqrt(2)),
    }


def airborne(mock, c) -> None:  # type: ignore[no-untyped-def]
    assert c.command(176, CUSTOM, GUIDED) == ACCEPTED
    assert c.command(400, 1) == ACCEPTED
    assert c.command(22, 0, 0, 0, 0, 0, 0, ALT) == ACCEPTED
    assert wait_for(lambda: abs(mock.snapshot()["position"][2] + ALT) < 0.05
                    and abs(mock.snapshot()["velocity"][2]) < 0.05, 30)


@pytest.mark.parametrize(("autopilot", "defaults"), [("ardupilot", AP_DEFAULTS), ("px4", PX4_DEFAULTS)])
def test_limits_served_with_the_real_defaults_and_settable(make_mock, autopilot, defaults) -> None:  # type: ignore[no-untyped-def]
    _, c = make_mock(autopilot, speed=2.0)
    for name, value in defaults.items():
        assert read_param(c, name) == pytest.approx(value), name
    name = next(iter(defaults))
    assert set_param(c, name, 2 * defaults[name]) == pytest.approx(2 * defaults[name])
    assert read_param(c, name) == pytest.approx(2 * defaults[name])


@pytest.mark.parametrize("shaping", [True, False])
def test_ardupilot_plan_beyond_the_limits_lags_and_overshoots(make_mock, shaping: bool) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=2.0, shaping=shaping, spool_up_s=0.5)
    airborne(mock, c)
    # Per axis v 3.86, a 3.16, j 10 (the companion's jerk bound): |v| 5.46, |a| 4.47 on the
    # diagonal, as the plan measured on SITL; over WPNAV_ACCEL 2.5 and PSC_JERK_XY 5.
    r = fly_diagonal(mock, c, 3.86, 3.16, 10.0)
    assert r["plan_speed"] == pytest.approx(5.46, abs=0.01) and r["plan_acc"] == pytest.approx(4.47, abs=0.01)
    if shaping:
        # SITL: flown up to 6.85 m/s, overshoot 3.36 m (before the companion braked).
        assert r["overshoot"] > 2.0, r
        assert r["peak_speed"] > r["plan_speed"] + 1.0, r
    else:
        assert r["overshoot"] < 0.7, r  # the kind mock of before: it followed any plan


def test_ardupilot_plan_within_the_limits_is_followed_closely(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=2.0, spool_up_s=0.5)
    airborne(mock, c)
    # |v| 2.83, |a| 2.26 (< WPNAV_ACCEL 2.5), |j| 4.5 (< PSC_JERK_XY 5).
    r = fly_diagonal(mock, c, 2.0, 1.6, 3.2)
    # SITL within its limits: 0.110 m RMS on time; allowance for this mock's ~60 ms lag.
    assert r["rms"] < 0.2, r
    assert r["overshoot"] < 0.4, r


def test_ardupilot_shaping_reads_the_live_parameters(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("ardupilot", speed=2.0, spool_up_s=0.5)
    airborne(mock, c)
    set_param(c, "WPNAV_ACCEL", 600.0)
    set_param(c, "PSC_JERK_XY", 20.0)
    r = fly_diagonal(mock, c, 3.86, 3.16, 10.0)
    assert r["overshoot"] < 0.8, r  # the same plan as above, within the raised limits


def test_px4_offboard_velocity_bound_by_mpc_parameters(make_mock) -> None:  # type: ignore[no-untyped-def]
    mock, c = make_mock("px4", speed=2.0)
    port = mock.addresses[0][1]
    assert set_param(c, "MPC_XY_VEL_MAX", 3.0) == pytest.approx(3.0)
    with Streamer(port, x=0.0, y=0.0, z=-4.0, mask=POS_ONLY) as hover:
        time.sleep(1.2 / mock.config.speed + 0.3)
        assert c.command(176, CUSTOM, 6, 0) == ACCEPTED
        assert c.command(400, 1) == ACCEPTED
        assert wait_for(lambda: mock.snapshot()["position"][2] < -3.9, 15)
        hover.setpoint = {"mask": VEL_ONLY, "vel": (6.0, 0.0, 3.0)}  # fast forward, fast down
        t0 = mock.snapshot()["t"]
        assert wait_for(lambda: mock.snapshot()["t"] - t0 > 2.5, 10)
        states = [r for r in records(mock, "state") if r["t"] >= t0 + 1.5 and not r["landed"]]
        hover.setpoint = {"x": 0.0, "y": 0.0, "z": -4.0, "mask": POS_ONLY}
    speeds = [math.hypot(r["vel"][0], r["vel"][1]) for r in states]
    down = [r["vel"][2] for r in states]
    assert 2.8 < max(speeds) <= 3.05  # MPC_XY_VEL_MAX, set live
    assert 1.3 < max(down) <= 1.55  # MPC_Z_VEL_MAX_DN 1.5
