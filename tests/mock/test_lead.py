"""Lag compensation on the calibrated mock: `setpoints.lead = "auto"` estimates the vehicle's
lag from telemetry, samples setpoints that far ahead on the verified plan, and flies the plan
closer than without it (tracking error measured against the plan at each sample's time)."""

from __future__ import annotations

import asyncio
import math
import time
from pathlib import Path
from typing import Any

import pytest
from companionkit import Events, service_for, serving, until

from companion.config import ConfigError, config_from_dict
from companion.wire.messages import read
from sitl_mock import MockAutopilot, MockConfig
from sitl_mock.vehicle import RESPONSES

# From the hover the takeoff leaves, three sides of the square (no transit leg from the hover to
# a first waypoint elsewhere: ~9 s of CI per flight)
MISSION = (b'{"id": "curve", "waypoints": [[0, 0, -1.5], [4, 0, -1.5], [4, 4, -1.5], [0, 4, -1.5]],'
           b' "durations": [2.5, 2.5, 2.5]}')


def test_lead_option() -> None:
    assert config_from_dict({"setpoints": {"lead": "auto"}}).setpoints.lead == "auto"
    assert config_from_dict({"setpoints": {"lead": 0.06}}).setpoints.lead == 0.06
    for bad in (0.6, -0.01, "fast", True):  # lead_max is 0.5 s by default (issue 26.5: PX4 lags ~0.3 s)
        with pytest.raises(ConfigError, match=r"setpoints\.lead"):
            config_from_dict({"setpoints": {"lead": bad}})


async def _fly(mock: MockAutopilot, lead: Any) -> tuple[float, Any, float]:
    svc = service_for(mock, setpoints={"lead": lead})
    Events(svc)
    errors: list[float] = []
    sample = svc.watch.on_position_sample
    assert sample is not None

    def record(now: float) -> None:
        sample(now)
        if svc.flight.state.value == "STREAMING" and svc.tracking.tracking_error is not None:
            errors.append(svc.tracking.tracking_error)

    svc.watch.on_position_sample = record
    async with serving(svc):
        await until(lambda: svc.link.state.position_problem() is None, 10, "position")
        await svc.commands.takeoff(1.5)
        await svc.navigator.on_mission(read("mission", MISSION, svc.cfg), time.monotonic())  # type: ignore[arg-type]
        await until(lambda: svc.flight.state.value == "STREAMING", 10, "streaming")
        await until(lambda: svc.flight.state.value == "HOLDING", 40, "mission complete")
        status = svc.status()
    rms = math.sqrt(sum(e * e for e in errors) / len(errors))
    return rms, status["lag_estimate_ms"], status["lead_ms"]


@pytest.mark.slow
def test_auto_lead_lowers_tracking_error_on_the_calibrated_mock(tmp_path: Path) -> None:
    figures = {}
    for lead in (0.0, "auto"):
        # the calibrated response on the ArduPilot flavour (its own): the PX4 flavour's estimate strays
        # 0.42 m from the setpoint as PX4 SIH's does (RMS 0.26 m), which would hide the lead's effect
        mock = MockAutopilot(MockConfig(autopilot="ardupilot", endpoints=["udpin:127.0.0.1:0"],
                                        vehicle=RESPONSES["calibrated"],
                                        log_path=str(tmp_path / f"{lead}.jsonl"))).start()
        try:
            figures[lead] = asyncio.run(_fly(mock, lead))
        finally:
            mock.stop()
    rms0, lag0, lead0 = figures[0.0]
    rms_auto, lag_auto, lead_auto = figures["auto"]
    print(f"tracking RMS without lead {rms0:.3f} m, with auto lead {rms_auto:.3f} m "
          f"(lag estimate {lag_auto} ms, lead {lead_auto} ms; without: lag estimate {lag0} ms)")
    assert lead0 == 0.0
    # the calibrated response: a 30 ms delay and half the acceleration feed-forward (~60 ms
    # effective lag on the demo's scenario 1); measured here: 32-38 ms, leading or not
    assert lag0 is not None and 25.0 <= lag0 <= 120.0
    assert 25.0 <= lead_auto <= 120.0 and lead_auto == pytest.approx(lag_auto, abs=0.5)
    assert rms_auto < 0.9 * rms0  # measured: 0.067-0.069 -> 0.041-0.042 m
