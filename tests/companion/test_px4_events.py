"""Decoding PX4 events with an events metadata file, and the reasons gathered around a refusal."""

from __future__ import annotations

import struct
import time
from pathlib import Path

import pytest

from companion.config import config_from_dict
from companion.wire.mavlink import MavlinkLink
from companion.wire.px4_events import EventsMetadata, MetadataError, default_cache_dir, ftp_path
from companion.wire.vehicle import Note

META = {
    "version": 2,
    "components": {"1": {
        "namespace": "px4",
        "enums": {
            "arm_disarm_reason_t": {"type": "uint8_t", "entries": {"4": {"name": "command_external",
                                                                         "description": "external command"}}},
            "navigation_mode_group_t": {"type": "uint32_t", "is_bitfield": True, "entries": {
                "1": {"name": "manual", "description": "Manual"}, "16": {"name": "loiter", "description": "Hold"},
                "16384": {"name": "offboard", "description": "Offboard"}}},
        },
        "event_groups": {"default": {"events": {
            # keys are 24-bit sub-ids, as PX4's all_events.json
            str(0x0102089D & 0xFFFFFF): {"name": "commander_arm_denied_resolve_failures",
                                         "message": "Arming denied: Resolve system health failures first"},
            "100": {"name": "armed_by", "message": "Armed by {1}",
                    "arguments": [{"type": "px4::enums::arm_disarm_reason_t", "name": "reason"}]},
            "101": {"name": "alt", "message": "Using default takeoff altitude: {1:.1m}",
                    "arguments": [{"type": "float", "name": "altitude"}]},
            "102": {"name": "modes", "message": "Not possible in {2} (<param>COM_X</param>)",
                    "arguments": [{"type": "uint8_t", "name": "pad"},
                                  {"type": "px4::enums::navigation_mode_group_t", "name": "modes"}]},
        }}},
    }},
}


def test_messages_in_words_with_arguments() -> None:
    meta = EventsMetadata(META)
    said = meta.describe(16910493, b"")
    assert said is not None and said.text == "Arming denied: Resolve system health failures first"
    assert said.name == "commander_arm_denied_resolve_failures"
    assert meta.describe((1 << 24) | 100, bytes([4])).text == "Armed by external command"  # type: ignore[union-attr]
    assert meta.describe((1 << 24) | 100, bytes([9])).text == "Armed by 9"  # type: ignore[union-attr]  # no entry
    alt = meta.describe((1 << 24) | 101, struct.pack("<f", 2.54))
    assert alt is not None and alt.text == "Using default takeoff altitude: 2.5 m"
    modes = meta.describe((1 << 24) | 102, struct.pack("<BI", 0, 16 | 16384))
    assert modes is not None and modes.text == "Not possible in Hold, Offboard (COM_X)"
    assert meta.describe((2 << 24) | 100, b"") is None  # another component's id
    assert meta.describe(12345, b"") is None


def test_malformed_metadata_is_refused() -> None:
    with pytest.raises(MetadataError):
        EventsMetadata({"version": 2})


def test_ftp_paths_of_mftp_uris() -> None:
    assert ftp_path("mftp://etc/extras/all_events.json.xz") == "etc/extras/all_events.json.xz"
    assert ftp_path("mftp://[;comp=1]etc/extras/x.json") == "etc/extras/x.json"


def test_refusal_reasons_are_px4_events_and_ardupilot_prearm_texts() -> None:
    link = MavlinkLink(config_from_dict({}))
    now = time.monotonic()
    notes = link.state.notes
    notes.append(Note(now - 5, "statustext", "PreArm: too early", "CRITICAL", words=True))  # before the window
    notes.append(Note(now, "statustext", "PreArm: Need Position Estimate", "CRITICAL", words=True))
    notes.append(Note(now, "statustext", "Arm: Throttle too high", "INFO", words=True))  # 'Arm:' at any level
    notes.append(Note(now, "event", "Arming check summary event", "PROTOCOL", 27825120, words=True))
    notes.append(Note(now, "event", "Navigation error: No valid position estimate", "ERROR", 30612409, words=True))
    notes.append(Note(now, "statustext", "PreArm: Need Position Estimate", "CRITICAL", words=True))  # once
    notes.append(Note(now, "statustext", "EKF3 IMU0 is using GPS", "INFO", words=True))  # not a reason
    assert link.reasons_around(now - 1, now + 1) == (
        "PreArm: Need Position Estimate", "Arm: Throttle too high", "Navigation error: No valid position estimate")


def test_cache_dir_follows_systemd_then_xdg(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setenv("CACHE_DIRECTORY", f"{tmp_path}/unit:{tmp_path}/other")
    assert default_cache_dir() == tmp_path / "unit"  # the unit's sandbox has no home
    monkeypatch.delenv("CACHE_DIRECTORY")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path))
    assert default_cache_dir() == tmp_path / "bezier-companion"


def test_enum_arguments_as_real_px4_names_them() -> None:
    """PX4 1.15's all_events.json names an argument's enum `px4::arm_disarm_reason_t` (no
    `enums::`), or bare within its component: the field saw "Armed by 4"."""
    real = {"version": 2, "components": {"1": {
        "namespace": "px4",
        "enums": META["components"]["1"]["enums"],  # type: ignore[index]
        "event_groups": {"default": {"events": {
            "9489139": {"name": "commander_armed_by", "message": "Armed by {1}",
                        "arguments": [{"name": "arg0", "type": "px4::arm_disarm_reason_t"}]},
            "10450063": {"name": "check_modes_attitude", "message": "No valid attitude estimate in {1}",
                         "arguments": [{"name": "modes", "type": "navigation_mode_group_t"}]},
        }}},
    }}}
    meta = EventsMetadata(real)
    armed = meta.describe((1 << 24) | 9489139, bytes([4]))
    assert armed is not None and armed.text == "Armed by external command"
    att = meta.describe((1 << 24) | 10450063, struct.pack("<I", 16))
    assert att is not None and att.text == "No valid attitude estimate in Hold"


def _note(at: float, name: str, text: str, level: str = "ERROR") -> Note:
    return Note(at, "event", text, level, 1, name, words=True)


def test_the_last_arming_check_report_is_the_reason_whenever_it_came() -> None:
    """Real PX4 SIH 1.15 (px4_1): the report 3.7 s before the `arm`, the refusal alone after it."""
    from companion.wire.px4_events import arming_report

    notes = [
        _note(90.0, "commander_arming_check_summary", "Arming check summary event", "PROTOCOL"),
        _note(90.01, "check_modes_attitude", "No valid attitude estimate", "ERROR"),  # an older report
        _note(100.0, "commander_arming_check_summary", "Arming check summary event", "PROTOCOL"),
        _note(100.003, "check_modes_attitude", "No valid attitude estimate", "CRITICAL"),
        _note(100.003, "check_modes_local_pos", "No valid local position estimate", "ERROR"),
        _note(100.004, "check_modes_mission", "No valid mission available", "INFO"),  # not a reason
        _note(100.004, "check_modes_local_pos", "No valid local position estimate", "ERROR"),  # once
        _note(100.004, "commander_health_summary", "Health report summary event", "PROTOCOL"),
        _note(105.2, "commander_arm_denied_resolve_failures", "Arming denied: Resolve system health failures first",
              "CRITICAL"),
    ]
    found = arming_report(notes, 105.3)
    assert found is not None
    age, said = found
    assert abs(age - 5.3) < 1e-6
    assert said == ("No valid attitude estimate", "No valid local position estimate")
    assert arming_report(notes, 100.0 + 31.0) is None  # too old to be the current state
    assert arming_report(notes[-1:], 105.3) is None  # no report heard
    ready = [_note(200.0, "commander_arming_check_summary", "Arming check summary event", "PROTOCOL"),
             _note(200.001, "commander_health_summary", "Health report summary event", "PROTOCOL")]
    assert arming_report(notes + ready, 201.0) == (1.0, ())  # the latest report: nothing fails
