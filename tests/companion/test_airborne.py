"""`airborne` follows the autopilot: its landed state, else height above the ground and speed."""

from __future__ import annotations

import numpy as np

from companion.autopilot import GROUND_FOR, AutopilotWatch
from companion.config import Config
from companion.flight import FlightState, State
from companion.report import Reporter
from companion.supervisor import Supervisor
from companion.wire.vehicle import VehicleState


class Link:
    def __init__(self) -> None:
        self.state = VehicleState(autopilot="ardupilot")


def watch(state: State = State.IDLE, airborne: bool = False) -> tuple[AutopilotWatch, Supervisor, VehicleState]:
    """The state is set from the start: learning the ground while disarmed does not read it."""
    fl, link = Supervisor(FlightState(state, airborne)), Link()
    w = AutopilotWatch(Config(), fl, link, Reporter(fl))  # type: ignore[arg-type]
    return w, fl, link.state


def at(st: VehicleState, z: float, v: float = 0.0, armed: bool = True) -> None:
    st.position = np.array([0.0, 0.0, z])
    st.velocity = np.array([0.0, 0.0, v])
    st.armed = armed


def test_without_a_landed_state_height_sets_and_rest_on_the_ground_clears_airborne() -> None:
    w, fl, st = watch(State.PILOT)  # a pilot flies it
    at(st, 0.02, armed=False)
    w.on_position(0.0)  # the ground, learnt while disarmed
    at(st, -2.0, 0.5)
    w.on_position(1.0)
    assert fl.airborne
    at(st, -0.05, 0.5)  # down, still moving: not yet
    w.on_position(2.0)
    assert fl.airborne
    at(st, 0.0, 0.05)
    w.on_position(3.0)
    w.on_position(3.0 + GROUND_FOR * 0.5)
    assert fl.airborne  # at rest on the ground, not long enough
    w.on_position(3.0 + GROUND_FOR + 0.01)
    assert not fl.airborne  # landed, still armed


def test_a_fresh_landed_state_is_what_counts() -> None:
    w, fl, st = watch(State.PILOT, airborne=True)
    at(st, 0.0, armed=False)
    w.on_position(0.0)
    st.last_landed_state = 10.0  # EXTENDED_SYS_STATE just arrived (in air, say)
    at(st, 0.0, 0.0)
    for t in (10.1, 10.5, 12.0):
        w.on_position(t)
    assert fl.airborne
    w.on_landed_state(1)  # MAV_LANDED_STATE_ON_GROUND
    assert not fl.airborne


def test_our_takeoff_decides_itself() -> None:
    w, fl, st = watch(State.TAKEOFF)
    at(st, 0.0, armed=False)
    w.on_position(0.0)
    at(st, -0.8, -0.8)
    w.on_position(1.0)
    assert not fl.airborne
