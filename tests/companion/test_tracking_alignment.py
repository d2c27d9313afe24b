"""Tracking error: a measured position against the setpoint of the measurement's own time."""

from __future__ import annotations

import time

import numpy as np

from companion.control import Control
from companion.setpoints import Feed, YawPolicy
from tests.companion.test_route import fly


class Target:
    feed: Feed | None = None


def test_error_uses_the_setpoint_of_the_measurement_time() -> None:
    ctl = Control(Target(), lambda sp: None, YawPolicy("fixed", 0.0, 0.5), 50.0)
    r = fly([[0.0, 6.0, -1.5]], [0.0, 0.0, -1.5], t0=0.0)
    mid = 0.5 * (r.trajectory.t0 + r.trajectory.t_end)
    t_base = time.monotonic() - (mid + 0.5)
    ctl._set(r.trajectory, t_base, True)
    measured_at = t_base + mid - 0.5  # a sample one second old, mid-flight
    where = r.trajectory.evaluate(np.array([mid - 0.5]))[0]
    assert ctl.tracking_error(where, measured_at) == 0.0 or ctl.tracking_error(where, measured_at) < 1e-9
    # against "now" the same, exact, sample would look a long way off
    now_err = float(np.linalg.norm(where - ctl.reference()))  # type: ignore[operator]
    assert now_err > 0.5
    ctl.release()
    assert ctl.tracking_error(where, measured_at) is None
