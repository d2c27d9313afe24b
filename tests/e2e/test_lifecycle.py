"""Lifecycle: a signal in flight brakes to a stop and hands the vehicle over to the autopilot's
own hold, which the mock must confirm, before the companion exits 0; a denied arm leaves the
autopilot in the mode it was in. One rig per test (each ends with the companion gone)."""

from __future__ import annotations

import signal
import subprocess
import time
from typing import Any

import numpy as np
import pytest
from e2e_rig import Rig

from companion.handover import HOLD_PROFILES
from companion.wire.vehicle import POSITION_ONLY_MASK

pytestmark = pytest.mark.slow

LONG = {"id": "long", "frame": "ned",
        "waypoints": [[4.0, 0.0, -1.5], [4.0, 4.0, -1.5], [0.0, 4.0, -1.5], [0.0, 0.0, -1.5]]}


# one diagonal leg (the bounds are per axis): ~3 m/s in its middle
DIAGONAL = {"id": "diagonal", "frame": "ned", "waypoints": [[15.0, 15.0, -1.5]]}


def _take_off_at_rest(rig: Rig, altitude: float) -> None:
    """Takeoff completes within tolerance of its altitude and at rest (not on the way up)."""
    since = rig.mark()
    rig.command("arm")
    rig.wait_event(lambda e: e["type"] == "state" and e.get("to") == "READY", 20, "armed/READY", since)
    ground = rig.control.state()["position"][2]
    since = rig.mark()
    rig.command("takeoff", altitude=altitude)
    rig.wait_event(lambda e: e["type"] == "state" and e.get("to") == "READY", 30, "takeoff complete", since)
    st = rig.control.state()  # within a few tens of ms of the declaration
    assert abs(st["position"][2] - (ground - altitude)) <= 0.2 + 0.02
    assert float(np.linalg.norm(st["velocity"])) <= 0.2 + 0.1


def _signal_in_flight(rig: Rig, sig: int) -> tuple[float, int, list[dict[str, Any]]]:
    _take_off_at_rest(rig, 1.5)
    since = rig.mark()
    rig.put("mission", LONG)
    rig.wait_event(lambda e: e["type"] == "state" and e.get("to") == "STREAMING", 15, "streaming", since)
    # well into the first leg, moving
    deadline = time.monotonic() + 15
    while (speed := float(np.linalg.norm(rig.control.state()["velocity"]))) < 1.0:
        assert time.monotonic() < deadline, f"test set-up: the vehicle must be moving ({speed:.2f} m/s)"
        time.sleep(0.02)
    t_sig = rig.mock_time()
    companion: subprocess.Popen[bytes] = rig.procs[1]
    companion.send_signal(sig)
    code = companion.wait(30)
    return t_sig, code, rig.log()


def test_px4_sigterm_at_3_m_s_exits_with_a_margin_to_exit_timeout(rig_factory: Any) -> None:
    """Issue 20: on PX4 SIH a SIGTERM at 2.89 m/s took 8.76 s of PX4's 9.5 s `exit_timeout` (systemd's
    TimeoutStopSec is 10 s): the braking waited for PX4's estimate under 0.2 m/s. With PX4's own
    rest speed (companion.handover HOLD_PROFILES) a real `python -m companion` process, SIGTERM at
    ~3 m/s on the PX4 mock (PX4 SIH's response, its estimate straying), exits 0, handed over,
    at least 2 s inside `exit_timeout`, timed from the signal to the process's exit."""
    rig: Rig = rig_factory("px4")
    _take_off_at_rest(rig, 1.5)
    since = rig.mark()
    rig.put("mission", DIAGONAL)
    rig.wait_event(lambda e: e["type"] == "state" and e.get("to") == "STREAMING", 15, "streaming", since)
    deadline = time.monotonic() + 20
    while (speed := float(np.linalg.norm(rig.control.state()["velocity"]))) < 2.85:
        assert time.monotonic() < deadline, f"test set-up: the vehicle must reach ~3 m/s ({speed:.2f} m/s)"
        time.sleep(0.02)
    companion: subprocess.Popen[bytes] = rig.procs[1]
    t0 = time.monotonic()
    companion.send_signal(signal.SIGTERM)
    code = companion.wait(30)
    took = time.monotonic() - t0
    assert code == 0, (rig.tmp / "px4-companion.err").read_text()[-3000:]
    budget = HOLD_PROFILES["px4"].exit_timeout
    assert took <= budget - 2.0, f"SIGTERM at {speed:.2f} m/s: the process exited after {took:.2f} s of {budget} s"
    held = [e for e in rig.events_since(0) if e["type"] == "handover"]
    assert held and held[-1]["held"] is True and held[-1]["mode"] == "LOITER", held


def _after(log: list[dict[str, Any]], t: float, kind: str) -> list[dict[str, Any]]:
    return [r for r in log if r["type"] == kind and r["t"] >= t]


@pytest.mark.parametrize(("autopilot", "sig"), [("px4", signal.SIGINT), ("ardupilot", signal.SIGTERM)])
def test_signal_in_flight_brakes_and_hands_over(rig_factory: Any, autopilot: str, sig: int) -> None:
    """The hand-over holds without a pilot (issue 20): PX4 AUTO.LOITER; ArduPilot stays in GUIDED
    holding a position target at the stop point (never LOITER, a pilot mode that descends with
    no RC input on ArduCopter). The vehicle still holds its altitude 10 s after the companion
    exited, read from the mock's own state."""
    rig: Rig = rig_factory(autopilot)
    t_sig, code, log = _signal_in_flight(rig, sig)
    assert code == 0, (rig.tmp / f"{autopilot}-companion.err").read_text()[-3000:]
    modes = _after(log, t_sig, "mode")
    failsafes = [r for r in _after(log, t_sig, "event") if r.get("event") == "failsafe"]
    assert not failsafes, failsafes
    applied = [r for r in _after(log, t_sig, "setpoint") if r["applied"]]
    if autopilot == "px4":
        assert modes and all(m["reason"] == "command" for m in modes), modes
        assert [m["to"] for m in modes] == ["LOITER"]
        t_hand = modes[0]["t"]
        hold_mode = "LOITER"
    else:
        assert modes == [], modes  # no mode change at all: GUIDED keeps the position target
        # the last setpoint applied is position-only, at rest at the verified stop's end
        last = applied[-1]
        assert last["type_mask"] == POSITION_ONLY_MASK, last
        t_hand = last["t"]
        hold_mode = "GUIDED"
    # braked to rest (by a verified stop) before the hand-over: slow when it happened
    at_hand = _after(log, t_hand - 0.05, "state")[:5]
    assert at_hand and max(float(np.linalg.norm(r["vel"])) for r in at_hand) <= 0.3
    # and the stop was ours: setpoints applied after the signal, before the hand-over
    assert len([r for r in applied if r["t"] < t_hand]) > 10
    # the autopilot holds the vehicle, armed, in the air, at its altitude for 10 s after the exit
    z0 = rig.control.state()["position"][2]
    t_end = time.monotonic() + 10.0
    while time.monotonic() < t_end:
        st = rig.control.state()
        assert st["mode"] == hold_mode and st["armed"] and not st["landed"], st
        assert abs(st["position"][2] - z0) <= 0.2, (st["position"], z0)
        assert float(np.linalg.norm(st["velocity"])) <= 0.2, st
        time.sleep(0.2)
    events = rig.events_since(0)
    held = [e for e in events if e["type"] == "handover"]
    assert held and held[-1]["held"] is True and held[-1]["mode"] == hold_mode, held
    assert any(e["type"] == "stopped" and e.get("handed_over") for e in events)


def test_denied_arm_restores_the_previous_mode(rig_factory: Any) -> None:
    rig: Rig = rig_factory("px4")
    before = rig.control.state()["mode"]
    assert before != "OFFBOARD"
    assert rig.control.reject_arming(True)["ok"]
    since = rig.mark()
    rig.command("arm")
    ev = rig.wait_event(lambda e: e["type"] == "refused" and e.get("command") == "arm", 20, "arm refused", since)
    assert "back in" in ev["reason"], ev["reason"]
    rig.wait_status(lambda s: s["mode"] == before and not s["armed"], 10, f"back in {before}")
    modes = [r for r in rig.log() if r["type"] == "mode"]
    assert [m["to"] for m in modes][-2:] == ["OFFBOARD", before]
    assert rig.state() == "IDLE"
