"""PX4's events in words through the companion, against the mock's metadata served over MAVLink FTP."""

from __future__ import annotations

import asyncio
import re
import time
from pathlib import Path
from typing import Any

from companionkit import Events, service_for, serving, until

from companion.wire.messages import Command
from companion.wire.px4_events import arming_report
from sitl_mock import MockAutopilot, MockConfig


def reported(svc: Any) -> bool:
    """The companion has heard an arming-check report (PX4 sends it when the checks change)."""
    return arming_report(svc.commands.events_heard, time.monotonic()) is not None


def test_arming_refusal_before_px4_is_ready_names_the_reason_in_words(tmp_path: Path) -> None:
    # a report every 3 s instead of PX4's 28, for the test's time
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"], px4_ready_s=600.0,
                                    px4_report_every_s=3.0, log_path=str(tmp_path / "f.jsonl"))).start()
    cache = tmp_path / "cache"

    async def go() -> None:
        svc = service_for(mock, mavlink={"events_cache_dir": str(cache)})
        events = Events(svc)
        async with serving(svc):
            px4 = svc.link.events
            await until(lambda: px4.metadata is not None, 20, f"the events metadata ({px4.status})")
            assert px4.source == "ftp" and list(cache.glob("px4-events-*.json"))
            await until(lambda: reported(svc), 10, "an arming-check report")
            await svc.commands.on_command(Command("arm"), time.monotonic())
            await until(lambda: events.of("refused"), 15, "the refusal")
            refused = events.of("refused")[0]
            assert refused["result"] == "MAV_RESULT_TEMPORARILY_REJECTED", refused
            # PX4's own words (its events metadata), not numbers
            assert "Arming denied: Resolve system health failures first" in refused["reasons"], refused
            assert "Navigation error: No valid position estimate" in refused["reasons"]
            # the estimator check PX4 SIH failed before ready (measured): vertical velocity
            assert "Vertical velocity unstable" in refused["reasons"]
            assert "Horizontal velocity unstable" not in refused["reasons"]
            assert "Resolve system health failures first" in refused["message"]
            assert not any("summary" in r for r in refused["reasons"])  # protocol events are not reasons
            relayed = [e for e in events.of("autopilot") if e.get("source") == "event"]
            assert relayed and all(e["text"] and not re.search(r"event \d", e["message"]) for e in relayed), relayed
            assert svc.link.state.mode == "LOITER" and not svc.link.state.armed

    try:
        asyncio.run(go())
        assert mock.px4 is not None and mock.px4.ftp.opened == 2  # the general file, the events file

        async def again() -> None:  # a restart on the same firmware: the cache, no FTP
            svc = service_for(mock, mavlink={"events_cache_dir": str(cache)})
            async with serving(svc):
                await until(lambda: svc.link.events.metadata is not None, 20, "the events metadata")
                assert svc.link.events.source == "cache"

        asyncio.run(again())
        assert mock.px4.ftp.opened == 2
    finally:
        mock.stop()


def test_events_without_metadata_say_why_they_are_numbers(tmp_path: Path) -> None:
    """An autopilot that serves no metadata (here: FTP answered by nobody): numbers, and why."""
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"], px4_ready_s=600.0,
                                    log_path=str(tmp_path / "f.jsonl"))).start()
    assert mock.px4 is not None
    mock.px4.on_ftp = lambda msg: None  # type: ignore[method-assign]

    async def go() -> None:
        svc = service_for(mock, mavlink={"events_cache_dir": str(tmp_path / "cache")})
        events = Events(svc)
        async with serving(svc):
            await until(lambda: "could not be had" in svc.link.events.status, 30, "the metadata to fail")
            await svc.commands.on_command(Command("arm"), time.monotonic())
            await until(lambda: events.of("refused"), 15, "the refusal")
            relayed = [e for e in events.of("autopilot") if e.get("source") == "event"]
            assert relayed and all("event 16910493" not in e["message"] or "could not be had" in e["message"]
                                   for e in relayed)
            assert any("could not be had" in e["message"] for e in relayed), relayed

    try:
        asyncio.run(go())
    finally:
        mock.stop()


def test_an_arm_refusal_names_the_arming_checks_reported_seconds_before(tmp_path: Path) -> None:
    """Real PX4 (SIH 1.15, px4_1..5) sends its arming-check report when the checks change, 3.7 s
    before the `arm` in the field, and with the refusal only "Arming denied: Resolve system health
    failures first". The mock does the same (reports 2.4 and 4.5 s after boot, then every 8 s
    here); the refusal still says what fails, from the report heard seconds before."""
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"], px4_ready_s=600.0,
                                    px4_report_every_s=8.0, log_path=str(tmp_path / "f.jsonl"))).start()
    assert mock.px4 is not None

    async def go() -> None:
        svc = service_for(mock, mavlink={"events_cache_dir": str(tmp_path / "cache")})
        events = Events(svc)
        async with serving(svc):
            await until(lambda: svc.link.events.metadata is not None, 20, "the events metadata")
            # past PX4's two reports after boot (sitl_mock.px4.REPORTS_AT), one heard
            await until(lambda: reported(svc) and mock.t - mock.boot_t > 4.6, 12, "an arming-check report")
            await asyncio.sleep(2.5)  # beyond the second before the ACK that is searched for reasons
            await svc.commands.on_command(Command("arm"), time.monotonic())
            await until(lambda: events.of("refused"), 15, "the refusal")
            refused = events.of("refused")[0]
            assert refused["result"] == "MAV_RESULT_TEMPORARILY_REJECTED", refused
            assert "Navigation error: No valid position estimate" in refused["reasons"], refused
            assert "Vertical velocity unstable" in refused["reasons"], refused
            assert "arming checks" in refused["message"] and "No valid position estimate" in refused["message"]
            checks = refused["arming_checks"]
            assert checks["age_s"] >= 2.5 and "Vertical velocity unstable" in checks["reasons"], checks

    try:
        asyncio.run(go())
    finally:
        mock.stop()
