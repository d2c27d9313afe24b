"""The setpoint process samples at the lead the service set, including one set before it ran.

The service sets the initial lead when it is built (and the autopilot's at link-up), before the
setpoint process is spawned; a lead posted to no child was lost, so the child sampled at lead 0
while the parent (status `lead_ms`, the immediate setpoints of a swap, the lag estimate) assumed
the lead it had set, and the first change of the lead then moved the stream along the plan by
the whole lead in one tick (0.37 s, ~0.6 m on PX4: the e2e flights' tracking brake).
"""

from __future__ import annotations

import socket
import threading
import time

import numpy as np

from companion.sendproc import Encoding, SetpointProcess
from companion.setpoints import Feed, Tick, YawPolicy
from planner_core import Trajectory

SPEED = 1.0  # m/s along x


def _line(t0: float, t1: float) -> Trajectory:
    """A straight constant-speed line, x = SPEED * t (one degree-9 segment)."""
    u = np.linspace(0.0, 1.0, 10)
    ctrl = np.zeros((1, 10, 3))
    ctrl[0, :, 0] = SPEED * (t0 + u * (t1 - t0))
    return Trajectory(np.array([t0, t1]), ctrl)


def test_a_lead_set_before_the_process_runs_is_the_one_it_samples_at() -> None:
    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(("127.0.0.1", 0))
    ticks: list[Tick] = []
    lock = threading.Lock()

    def on_tick(tick: Tick) -> None:
        with lock:
            ticks.append(tick)

    sender = SetpointProcess(50.0, lambda: (sock.fileno(), True, Encoding(255, 191, 1, 1, None, time.monotonic())),
                             YawPolicy("fixed", 0.0, 0.3), on_tick, lambda exc: None)
    sender.lead = 0.3  # as the service does at construction, before start
    sender.start()
    try:
        t_base = time.monotonic()
        sender.feed = Feed(_line(0.0, 100.0), t_base)
        time.sleep(0.5)
        with lock:
            got = [t for t in ticks if t.setpoint is not None]
        assert len(got) >= 10
        # each setpoint is the plan at (send time - t_base) + lead
        leads = [float(t.setpoint.position[0]) / SPEED - (t.now - t_base) for t in got]
        assert np.allclose(leads, 0.3, atol=1e-6), leads[:5]
    finally:
        sender.stop()
        sock.close()
