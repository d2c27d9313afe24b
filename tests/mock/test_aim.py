"""The aim beyond the plan (`[setpoints] accel_lead`) per autopilot, flown on the mock.

With "autopilot" (the default) the companion aims ArduCopter's measured k F once an ArduPilot
autopilot is found at link-up, and nothing for PX4 (not measured); flown through the mock's
calibrated response (half of the acceleration feed-forward used, like ArduCopter) it lowers the
tracking error the companion itself measures against the plan.
"""

from __future__ import annotations

import asyncio
import math
import time
from pathlib import Path
from typing import Any

import pytest
from companionkit import Events, service_for, serving, until

from companion.config import ConfigError, config_from_dict
from companion.lag import MEASURED_AIM, initial_aim
from companion.wire.messages import read
from sitl_mock import MockAutopilot, MockConfig
from sitl_mock.vehicle import RESPONSES

# From the hover the takeoff leaves (no transit leg to a first waypoint elsewhere: ~9 s of CI each)
MISSION = (b'{"id": "curve", "waypoints": [[0, 0, -1.5], [4, 0, -1.5], [4, 4, -1.5], [0, 4, -1.5]],'
           b' "durations": [2.5, 2.5, 2.5]}')


def test_aim_option() -> None:
    assert config_from_dict({}).setpoints.accel_lead == "autopilot"
    assert config_from_dict({"setpoints": {"accel_lead": 0.05, "accel_lead_tc": 0.5}}).setpoints.accel_lead == 0.05
    for bad in (-0.01, 1.5, "more", True):
        with pytest.raises(ConfigError, match=r"setpoints\.accel_lead"):
            config_from_dict({"setpoints": {"accel_lead": bad}})
    assert initial_aim("autopilot", 1.0, "ardupilot") == MEASURED_AIM["ardupilot"] == (0.09, 1.0)
    assert initial_aim("autopilot", 1.0, "px4") == (0.0, 0.0)
    assert initial_aim("autopilot", 1.0, None) == (0.0, 0.0)  # before an autopilot is found
    assert initial_aim(0.03, 0.5, "px4") == (0.03, 0.5)


async def _fly(mock: MockAutopilot, aim: Any, **setpoints: Any) -> tuple[float, float, float]:
    svc = service_for(mock, setpoints={"accel_lead": aim, "lead": 0.06, **setpoints})
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
        k, tc = svc.sender.accel_lead, svc.sender.accel_lead_tc
        status = svc.status()
        assert (status["accel_lead"], status["accel_lead_tc"]) == (k, tc)  # the aim flown, as status says it
        await until(lambda: svc.flight.state.value == "HOLDING", 40, "mission complete")
    rms = math.sqrt(sum(e * e for e in errors) / len(errors))
    return rms, k, tc


async def _linked(mock: MockAutopilot) -> tuple[float, float]:
    svc = service_for(mock)
    async with serving(svc):
        await until(lambda: svc.link.state.autopilot == "px4" and svc.link.state.position_problem() is None, 10,
                    "link-up")
        status = svc.status()
        assert (status["accel_lead"], status["accel_lead_tc"]) == (svc.sender.accel_lead, svc.sender.accel_lead_tc)
        # no horizontal terms by default either (PX4 SIH's are not the mock's response): status says so
        assert status["aim_horizontal"] == [] and svc.sender.aim_horizontal == ()
        return svc.sender.accel_lead, svc.sender.accel_lead_tc


def test_no_aim_on_px4_after_link_up() -> None:
    """PX4's response was not measured for an aim: with the default, none once PX4 is found."""
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"], px4_ready_s=0.0)).start()
    try:
        assert asyncio.run(_linked(mock)) == (0.0, 0.0)
    finally:
        mock.stop()


@pytest.mark.slow
def test_the_autopilot_aim_is_set_at_link_up_and_lowers_the_tracking_error(tmp_path: Path) -> None:
    figures = {}
    for aim in (0.0, "autopilot"):
        mock = MockAutopilot(MockConfig(autopilot="ardupilot", endpoints=["udpin:127.0.0.1:0"],
                                        vehicle=RESPONSES["calibrated"], log_path=str(tmp_path / f"{aim}.jsonl"))).start()
        try:
            figures[aim] = asyncio.run(_fly(mock, aim))
        finally:
            mock.stop()
    rms0, k0, _ = figures[0.0]
    rms_aim, k, tc = figures["autopilot"]
    print(f"ardupilot: tracking RMS without aim {rms0:.3f} m, with the autopilot's aim {rms_aim:.3f} m (k {k}, tc {tc})")
    assert k0 == 0.0
    assert (k, tc) == MEASURED_AIM["ardupilot"]
    assert rms_aim < 0.8 * rms0


async def _linked_with(mock: MockAutopilot, terms: list[list[float]]) -> tuple[Any, Any]:
    svc = service_for(mock, setpoints={"aim_horizontal": terms})
    async with serving(svc):
        await until(lambda: svc.link.state.autopilot == "px4", 10, "link-up")
        return svc.sender.aim_horizontal, svc.status()["aim_horizontal"]


def test_configured_horizontal_terms_are_flown_and_said() -> None:
    from companion.lag import PX4_SIH_AIM_HORIZONTAL

    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"], px4_ready_s=0.0)).start()
    try:
        terms = [list(t) for t in PX4_SIH_AIM_HORIZONTAL]
        sent, said = asyncio.run(_linked_with(mock, terms))
    finally:
        mock.stop()
    assert sent == PX4_SIH_AIM_HORIZONTAL and said == terms


@pytest.mark.slow
def test_px4_sih_s_horizontal_aim_takes_up_its_slow_response(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """On the mock's PX4 response with SIH's drag and PX4's velocity integral (px4_sih_drag,
    which trails a plan as PX4 SIH did), PX4 SIH's measured terms with its 0.08 s lag fly the
    plan far closer than the 0.33 s lead alone (PX4 SIH: 0.46-0.58 -> 0.21-0.31 m RMS)."""
    from companion.lag import PX4_SIH_AIM_HORIZONTAL
    from sitl_mock import px4

    # the estimate's wander (stock SIH's; with EKF2's noise set to SIH's it is 0.08 m) is not
    # what is judged here: the response is
    monkeypatch.setattr(px4, "OFFBOARD_WANDER_M", 0.0)
    runs = {"lead": {"lead": 0.33}, "aim": {"lead": 0.08, "aim_horizontal": [list(t) for t in PX4_SIH_AIM_HORIZONTAL]}}
    figures = {}
    for name, setpoints in runs.items():
        mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"], px4_ready_s=0.0,
                                        px4_drift_m=0.0, vehicle=RESPONSES["px4_sih_drag"],
                                        log_path=str(tmp_path / f"{name}.jsonl"))).start()
        try:
            figures[name] = asyncio.run(_fly(mock, 0.0, **setpoints))[0]
        finally:
            mock.stop()
    print(f"px4_sih_drag: tracking RMS with the 0.33 s lead {figures['lead']:.3f} m, "
          f"with 0.08 s and the aim {figures['aim']:.3f} m")
    assert figures["aim"] < 0.6 * figures["lead"]
