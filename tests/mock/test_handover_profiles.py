"""The hand-over's confirmation is per autopilot (docs/handover.md, "Confirmed by watching the
vehicle"): PX4's AUTO.LOITER estimate wanders at up to 0.5-0.65 m/s while the vehicle holds
(real PX4 SIH 1.15, five hand-overs measured), which ArduPilot's thresholds (0.5 m/s) took
for a moving vehicle; a vehicle that really sinks is still caught on both. In process: the
service against the in-process mock, stopped as SIGTERM stops it (`requested`), after a takeoff."""

from __future__ import annotations

import asyncio
import dataclasses
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
from companionkit import Events, service_for, up

from companion.config import config_from_dict
from companion.handover import HOLD_PROFILES, hold_profile
from sitl_mock import MockAutopilot, MockConfig


def _mock(tmp_path: Path, autopilot: str) -> MockAutopilot:
    return MockAutopilot(MockConfig(autopilot=autopilot, endpoints=["udpin:127.0.0.1:0"], px4_ready_s=0.0,
                                    log_path=str(tmp_path / "flight.jsonl"), log_rate_hz=50)).start()


def _as_px4_does(mock: MockAutopilot, mode: str, stop: threading.Event) -> None:
    """Nothing added: the PX4 mock's own AUTO.LOITER after OFFBOARD reports the estimate
    wandering as PX4 SIH's did (sitl_mock.px4 LOITER_WANDER_*: 0.6 m/s horizontal, 0.25 m/s
    vertical; measured up to 0.65 and 0.31) while the vehicle itself holds."""


def _push_down_in(mock: MockAutopilot, mode: str, stop: threading.Event) -> None:
    """Once the vehicle is in `mode`, a strong downward gust: it sinks as a pilot mode with no
    pilot input does (ArduCopter LOITER: 2.5 m/s)."""
    while not stop.is_set():
        if mock.snapshot()["mode"] == mode:
            mock.wind = np.array([0.0, 0.0, 40.0])
            return
        time.sleep(0.01)


async def _fly_then_stop(mock: MockAutopilot, **safety: Any) -> tuple[bool, Events, float]:
    svc = service_for(mock, safety={"takeoff_altitude": 1.5, **safety})
    events = Events(svc)
    task = asyncio.create_task(svc.run())
    await up(svc, task)
    await svc.commands.takeoff(1.5)
    assert svc.flight.state.value == "READY" and svc.flight.airborne
    await asyncio.sleep(0.3)
    t0 = time.monotonic()
    svc.requested.set()
    handed_over = await asyncio.wait_for(task, 30)
    return handed_over, events, time.monotonic() - t0


def _after_flying(disturb: Any, mock: MockAutopilot, mode: str, stop: threading.Event) -> None:
    """`disturb` once the vehicle is back in `mode` after flying in another (PX4 boots in LOITER)."""
    while not stop.is_set() and not (mock.snapshot()["mode"] != mode and mock.snapshot()["armed"]):
        time.sleep(0.01)
    disturb(mock, mode, stop)


def _run(tmp_path: Path, autopilot: str, disturb: Any, mode: str, **safety: Any) -> tuple[bool, Events, float]:
    mock = _mock(tmp_path, autopilot)
    stop = threading.Event()
    th = threading.Thread(target=_after_flying, args=(disturb, mock, mode, stop), daemon=True)
    th.start()
    try:
        return asyncio.run(_fly_then_stop(mock, **safety))
    finally:
        stop.set()
        mock.stop()


def test_px4_loiter_with_a_wandering_estimate_is_a_hold(tmp_path: Path) -> None:
    handed_over, events, took = _run(tmp_path, "px4", _as_px4_does, "LOITER")
    last = events.of("handover")[-1]
    assert handed_over is True, last
    assert last["held"] is True and last["mode"] == "LOITER", last
    assert 0.5 < last["speed_max"] < 1.0, last  # above ArduPilot's 0.5 m/s, within PX4's profile
    assert last["limits"]["speed"] == HOLD_PROFILES["px4"].speed_tolerance
    assert took < HOLD_PROFILES["px4"].exit_timeout
    assert events.of("stopped")[-1]["handed_over"] is True


def test_px4_loiter_that_sinks_is_still_caught(tmp_path: Path) -> None:
    handed_over, events, _ = _run(tmp_path, "px4", _push_down_in, "LOITER")
    last = events.of("handover")[-1]
    assert handed_over is False, last
    assert last["held"] is False and "descend" in last["message"], last
    assert events.of("stopped")[-1]["handed_over"] is False


def test_the_same_wandering_estimate_with_ardupilot_s_thresholds_fails(tmp_path: Path) -> None:
    # the [safety] keys override the profile: PX4 with ArduPilot's figures is the old behaviour
    ap = HOLD_PROFILES["ardupilot"]
    handed_over, events, _ = _run(tmp_path, "px4", _as_px4_does, "LOITER",
                                  hold_speed_tolerance=ap.speed_tolerance, hold_altitude_tolerance=ap.altitude_tolerance)
    last = events.of("handover")[-1]
    assert handed_over is False and last["held"] is False and "moves at" in last["message"], last
    assert "[safety] hold_" in last["message"]


def test_profiles_rest_on_the_measured_figures() -> None:
    px4, ap = HOLD_PROFILES["px4"], HOLD_PROFILES["ardupilot"]
    # PX4 SIH 1.15 (five hand-overs): estimate speed while holding up to 0.65 m/s, altitude within 0.41 m
    assert px4.speed_tolerance > 0.65 and px4.altitude_tolerance > 0.41
    # the braking before the hand-over waits for a speed PX4's estimate reaches at rest (issue 20:
    # 0.47-0.65 m/s in AUTO.LOITER; the wait for 0.2 m/s ran out, the exit took 8.76 of 9.5 s)
    assert 0.65 < px4.rest_speed < px4.speed_tolerance
    # ArduCopter 4.6 (four hand-overs): speed <= 0.19 m/s, altitude change <= 0.04 m
    assert ap.speed_tolerance > 0.19 and ap.altitude_tolerance > 0.04
    for p in (px4, ap):
        # a pilot-mode descent at 2.5 m/s is above the speed tolerance and leaves the altitude
        # tolerance within 0.4 s
        assert p.speed_tolerance < 2.5 and p.altitude_tolerance / 2.5 <= 0.4
        assert p.exit_timeout < 10.0  # systemd's TimeoutStopSec
        assert p.confirm + p.settle + 2.0 <= p.exit_timeout  # braking ~2 s at 3.3 m/s, then the watch


def test_safety_keys_override_the_profile() -> None:
    cfg = config_from_dict({"safety": {"hold_speed_tolerance": 0.7, "exit_timeout": 6.0}})
    p = hold_profile(cfg.safety, "px4")
    assert (p.speed_tolerance, p.exit_timeout) == (0.7, 6.0)
    assert p.altitude_tolerance == HOLD_PROFILES["px4"].altitude_tolerance
    assert hold_profile(cfg.safety, "ardupilot").confirm == HOLD_PROFILES["ardupilot"].confirm
    # ArduPilot's rest speed is [safety] rest_speed's (0 in its profile), PX4's its own
    ap = hold_profile(config_from_dict({}).safety, None)
    assert ap == dataclasses.replace(HOLD_PROFILES["ardupilot"], rest_speed=config_from_dict({}).safety.rest_speed)
    assert hold_profile(config_from_dict({"safety": {"rest_speed": 0.3}}).safety, "ardupilot").rest_speed == 0.3
    assert hold_profile(config_from_dict({"safety": {"rest_speed": 0.3}}).safety, "px4").rest_speed == 0.7
    assert hold_profile(config_from_dict({"safety": {"hold_rest_speed": 0.5}}).safety, "px4").rest_speed == 0.5


def _nothing(mock: MockAutopilot, mode: str, stop: threading.Event) -> None:
    return None


def test_a_short_hold_confirm_is_kept_once_the_vehicle_is_at_rest(tmp_path: Path) -> None:
    """`[safety] hold_confirm = 0.5` (the fleet demo's): the settle time does not lengthen the
    watch of a vehicle already at rest (ArduCopter: GUIDED holding the stop point)."""
    handed_over, events, took = _run(tmp_path, "ardupilot", _nothing, "GUIDED", hold_confirm=0.5, exit_timeout=4.0)
    last = events.of("handover")[-1]
    assert handed_over is True and last["held"] is True and last["mode"] == "GUIDED", last
    assert last["watched_s"] < 1.0, last
    assert took < 4.0
