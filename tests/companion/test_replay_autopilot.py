"""Replay of the autopilot watch's steps: an AutopilotWatch and a Supervisor wired to a real
Recorder as the service wires them, driven through a flight by what the link would report
(heartbeats, positions, landed states, PX4 events, link checks), recorded into a real MCAP
file; replay runs every step again (exit 0) and finds each step's events among the
transitions; a changed step, a removed one, one the recorder dropped, a transition made
outside the watch, a flight state replaced behind the supervisor's back are each named by
their seq (exit 1); a step record cannot make replay load anything but the rules' own types."""

from __future__ import annotations

import base64
import json
import os
import pickle
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from pymavlink import mavutil
from pymavlink.dialects.v20 import common as mavlink2
from recorder_support import config, schema_checked
from test_replay_transitions import rewrite

from companion import channels as ch
from companion import replay, replay_autopilot, replay_cli
from companion.autopilot import AutopilotWatch
from companion.flight import FlightState, State
from companion.recorder import Recorder
from companion.report import Reporter
from companion.supervisor import (
    Armed,
    ArmRequested,
    ControlTaken,
    ControlTakenBack,
    HeightReport,
    Supervisor,
    TakingControl,
)
from companion.wire.vehicle import Note, VehicleState

TOPIC = "/autopilot/step"


class Link:
    def __init__(self) -> None:
        self.state = VehicleState(autopilot="px4")


def msg(**fields: Any) -> Any:
    """A received message as the watch reads it: its fields and its source (the autopilot's)."""
    return SimpleNamespace(get_srcSystem=lambda: 1, get_srcComponent=lambda: 1, **fields)


class Flight:
    """The watch, the supervisor and the link state, wired to `rec` as the service wires them."""

    def __init__(self, rec: Recorder) -> None:
        self.rec = rec
        self.writing = False  # the writer thread runs: each call waits for it to take what was queued
        self.sup = Supervisor()
        self.sup.connect(observe=rec.transition)
        self.link = Link()
        self.st = self.link.state
        self.watch = AutopilotWatch(rec.cfg, self.sup, self.link, Reporter(self.sup))  # type: ignore[arg-type]
        self.watch.connect(observe=rec.autopilot_step)

    def settle(self) -> None:
        """A small queue must not overflow here: the drops a test wants are made on purpose."""
        deadline = time.monotonic() + 10
        while self.writing and self.rec.stats()["queued"] and time.monotonic() < deadline:
            time.sleep(0.001)

    def handle(self, *events: Any) -> None:
        for event in events:
            self.settle()
            self.sup.handle(event)

    def check(self) -> None:
        self.settle()
        self.watch.check_link()

    def heartbeat(self, mode: str, armed: bool) -> None:
        """PX4's heartbeat in `mode`, as the link's one reader takes it (the fields as received)."""
        self.settle()
        base, main, sub = mavutil.px4_map[mode]
        hb = mavlink2.MAVLink_heartbeat_message(mavlink2.MAV_TYPE_QUADROTOR, mavlink2.MAV_AUTOPILOT_PX4,
                                                base | (mavlink2.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0),
                                                (main << 16) | (sub << 24), 4, 3)
        hb._header = mavlink2.MAVLink_header(0, srcSystem=1, srcComponent=1)
        assert self.st.take("HEARTBEAT", hb, time.monotonic(), 1)
        assert (self.st.mode, self.st.armed) == (mode, armed)
        self.watch.on_message("HEARTBEAT", hb)

    def position(self, z: float, vz: float = 0.0) -> None:
        self.settle()
        self.st.position, self.st.velocity = np.array([0.0, 0.0, z]), np.array([0.0, 0.0, vz])
        self.st.last_message = time.monotonic()
        self.watch.on_message("LOCAL_POSITION_NED", msg())

    def landed(self, state: int) -> None:
        self.settle()
        self.st.landed_state, self.st.last_landed_state = state, time.monotonic()
        self.watch.on_message("EXTENDED_SYS_STATE", msg(landed_state=state))

    def event(self, sequence: int) -> None:
        self.settle()
        self.st.notes.append(Note(time.monotonic(), "event", f"event {sequence}", "INFO", 1000 + sequence))
        self.watch.on_message("EVENT", msg(sequence=sequence))


def fly(f: Flight, meddle: Callable[[Flight], None] | None = None) -> None:
    """Found, the ground learnt, armed by us, up by height, a resent PX4 event, the link lost
    and restored, control taken back, a pilot takeover, landed and disarmed."""
    f.heartbeat("LOITER", armed=False)
    f.position(0.1)
    f.landed(1)  # on the ground
    f.handle(ControlTaken(), TakingControl("arm command"), ArmRequested(), Armed("OFFBOARD"))
    f.heartbeat("OFFBOARD", armed=True)
    f.st.last_landed_state = -np.inf  # an autopilot without EXTENDED_SYS_STATE from here on
    for z in (0.0, -0.4, -1.2, -1.5):
        f.position(z, -0.5)
    f.event(5)
    f.event(5)  # resent
    f.check()  # heard: nothing
    if meddle is not None:
        meddle(f)
    f.st.last_heartbeat = f.st.last_message = time.monotonic() - 10.0
    f.check()  # silent: lost, a failsafe
    f.heartbeat("OFFBOARD", armed=True)  # restored
    f.handle(ControlTaken(), TakingControl("start"), ControlTakenBack("OFFBOARD"))
    f.heartbeat("POSCTL", armed=True)  # a pilot takes over
    f.landed(1)
    f.heartbeat("POSCTL", armed=False)
    f.position(0.1)


def recorded(tmp_path: Path, queue: int = 4096, early: int = 0,
             meddle: Callable[[Flight], None] | None = None) -> tuple[Path, Recorder, Flight]:
    """`early`: a heartbeat and as many link checks before the writer thread starts (they wait
    in the queue, or are dropped)."""
    rec = Recorder(config(tmp_path, queue=queue))
    f = Flight(rec)
    if early:
        f.heartbeat("LOITER", armed=False)
    for _ in range(early):
        f.watch.check_link()
    rec.open()
    f.writing = True
    fly(f, meddle)
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    return path, rec, f


def steps(path: Path) -> list[dict[str, Any]]:
    with open(path, "rb") as fh:
        return [json.loads(m.data) for _s, _c, m in make_reader(fh).iter_messages(topics=[TOPIC])]


def with_values(rec: dict[str, Any], *values: Any) -> dict[str, Any]:
    """`rec` holding these six values, JSON and pickle alike (as a recorder would write them)."""
    return {**rec, **json.loads(ch.dumps(ch.step_fields(*values))),
            "pickle": base64.b64encode(pickle.dumps(values, protocol=5)).decode()}


def run(path: Path, capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    code = replay_cli.main([str(path), *args])
    return code, capsys.readouterr().out


def line(out: str) -> str:
    return next(ln for ln in out.splitlines() if ln.startswith("autopilot steps:"))


def seq_of(recs: list[dict[str, Any]], pred: Callable[[dict[str, Any]], bool]) -> int:
    return int(next(r for r in recs if pred(r))["seq"])


def test_every_step_is_recorded_and_replays_with_its_events_the_transitions(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, rec, f = recorded(tmp_path)
    recs = steps(path)
    assert rec.dropped == {} and [r["seq"] for r in recs] == list(range(1, len(recs) + 1))
    kinds = [r["reading"]["type"] for r in recs]
    assert kinds.count("HeartbeatSeen") == 5 and kinds.count("PositionSeen") == 6 and kinds.count("LinkCheck") == 2
    outputs = [o["type"] for r in recs for o in r["outputs"]]
    for made in ("LinkFound", "GroundLearnt", "LandedStateReport", "HeightReport", "Relay", "LinkLost",
                 "LinkRestored", "ModeReport", "Disarmed"):
        assert made in outputs, made
    assert outputs.count("Relay") == 1  # the resent event is not relayed again
    assert f.sup.state is State.IDLE  # the pilot's flight, landed and disarmed
    # the readable part validates against the channel's schema, which the file carries
    assert schema_checked(path, TOPIC, "bezier.AutopilotStep") == recs
    events = sum(1 for o in outputs if o not in ("LinkFound", "LinkRestored", "Relay"))
    code, out = run(path, capsys)
    assert code == 0, out
    assert f"autopilot steps: {len(recs)} of {len(recs)} reproduced ({events} events, each a recorded transition)" \
        in out.splitlines()
    beats = kinds.count("HeartbeatSeen")
    assert f"heartbeats: {beats} of {beats} read again alike (mode and armed from each one's fields as received)" \
        in out.splitlines()


def test_a_changed_state_after_is_found_with_its_seq_and_field(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    path, _rec, _f = recorded(tmp_path / "rec")
    recs = steps(path)
    seq = seq_of(recs, lambda r: r["after"]["lost_at"] is not None)

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        if r["seq"] != seq:
            return r
        before, flight, reading, now, after, outputs = replay_autopilot.loads_step(r["pickle"])
        return with_values(r, before, flight, reading, now, replace(after, lost_at=now - 1.0), outputs)

    code, out = run(rewrite(path, tmp_path / "changed.mcap", edit, topic=TOPIC), capsys)
    assert code == 1, out
    said = line(out)
    assert f"first difference: seq {seq} LinkCheck(" in said and "after.lost_at: recorded" in said, said
    # and the next step no longer starts where this one (as recorded) ended
    assert f"autopilot steps: {len(recs) - 2} of {len(recs)} reproduced" in said


def test_a_changed_event_is_found(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A takeover recorded as put down to a stall: the step's outputs differ on replay."""
    path, _rec, _f = recorded(tmp_path / "rec")
    seq = seq_of(steps(path), lambda r: any(o["type"] == "ModeReport" and o["fields"]["mode"] == "POSCTL"
                                            and r["flight"]["state"] == "READY" for o in r["outputs"]))

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        if r["seq"] != seq:
            return r
        before, flight, reading, now, after, (hb, report) = replay_autopilot.loads_step(r["pickle"])
        return with_values(r, before, flight, reading, now, after, (hb, replace(report, stalled=True)))

    code, out = run(rewrite(path, tmp_path / "changed.mcap", edit, topic=TOPIC), capsys)
    assert code == 1, out
    assert f"first difference: seq {seq} HeartbeatSeen(autopilot='px4', mode='POSCTL'" in line(out)
    assert "outputs[1].stalled: recorded True, replayed False" in line(out)


def test_a_readable_part_that_is_not_the_pickled_value_is_a_difference(tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    path, _rec, _f = recorded(tmp_path / "rec")

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "reading": {**r["reading"], "fields": {**r["reading"]["fields"], "mode": "OFFBOARD"}}} \
            if r["seq"] == 1 else r

    code, out = run(rewrite(path, tmp_path / "json.mcap", edit, topic=TOPIC), capsys)
    assert code == 1 and "seq 1 HeartbeatSeen(autopilot='px4', mode='LOITER'" in line(out)
    assert "the record's reading (JSON) is not its pickled value" in line(out)


def test_a_removed_step_is_a_gap_and_its_events_made_by_no_step(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    path, _rec, _f = recorded(tmp_path / "rec")
    recs = steps(path)
    seq = seq_of(recs, lambda r: any(o["type"] == "HeightReport" for o in r["outputs"]))
    code, out = run(rewrite(path, tmp_path / "removed.mcap", lambda r: None if r["seq"] == seq else r, topic=TOPIC),
                    capsys, "--keep-going")
    assert code == 1, out
    assert (f"autopilot steps: {len(recs) - 1} of {len(recs)} reproduced; first difference: seq {seq} missing "
            "(1 record: dropped by the recorder, or removed)") in out
    assert "was made by no recorded autopilot step" in out and "HeightReport(airborne=True)" in out


def test_steps_the_recorder_dropped_are_counted_and_the_gap_named(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """A real drop: link checks before the writer thread starts, into a queue of 4 (the
    transitions share it): the rest are dropped and counted under autopilot_step."""
    path, rec, _f = recorded(tmp_path, queue=4, early=8)
    # queued: the heartbeat's step, its two transitions, the first check; dropped: the 7 others
    assert rec.dropped == {"autopilot_step": 7}
    assert json.loads(replay.recorded_metadata(str(path))["recorder"]["dropped"]) == {"autopilot_step": 7}
    code, out = run(path, capsys, "--keep-going")
    assert code == 1, out
    n = len(steps(path)) + 7
    assert f"autopilot steps: {n - 7} of {n} reproduced; first difference: seq 3 to 9 missing (7 records" in line(out)
    assert "also: the recorder dropped 7 autopilot step records in this run" in out
    assert "transitions: " in out and "transitions: none" not in out and "dropped 7 transition" not in out


def test_a_transition_made_outside_the_watch_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Nothing edited after the flight: a HeightReport handed to the supervisor by something
    else than the watch; every step on its own replays."""
    def meddle(f: Flight) -> None:
        f.handle(HeightReport(airborne=False))

    path, _rec, _f = recorded(tmp_path, meddle=meddle)
    code, out = run(path, capsys)
    assert code == 1, out
    said = line(out)
    assert said.startswith(f"autopilot steps: {len(steps(path))} of {len(steps(path))} reproduced; first difference")
    assert "HeightReport(airborne=False) was made by no recorded autopilot step" in said
    assert "transitions: " in out and "transitions: none" not in out


def test_a_flight_state_replaced_behind_the_supervisor_is_what_a_step_read(tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture[str]) -> None:
    def meddle(f: Flight) -> None:
        f.sup._now = replace(f.sup.value, airborne=False)

    path, _rec, _f = recorded(tmp_path, meddle=meddle)
    code, out = run(path, capsys)
    assert code == 1, out
    assert "read another flight state than the supervisor's (flight.airborne: transition" in line(out)


def test_a_file_without_steps_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _rec, _f = recorded(tmp_path / "rec")
    code, out = run(rewrite(path, tmp_path / "none.mcap", lambda r: None, topic=TOPIC), capsys)
    assert code == 0, out
    assert "autopilot steps: none recorded" in out.splitlines()


class _Evil:
    def __reduce__(self) -> Any:
        return (os.system, ("echo pwned > pwned.txt",))


def test_a_step_record_cannot_name_anything_else(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    path, _rec, _f = recorded(tmp_path / "rec")

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "pickle": base64.b64encode(pickle.dumps((None, FlightState(), _Evil(), 0.0, None, ()))).decode()}

    assert replay_cli.main([str(rewrite(path, tmp_path / "evil.mcap", edit, topic=TOPIC))]) == 2
    assert "replay does not load posix.system from an autopilot step record" in capsys.readouterr().err
    assert not (tmp_path / "pwned.txt").exists()


def test_an_observer_that_fails_never_keeps_an_event_from_the_supervisor() -> None:
    rec = Recorder(config(""))
    f = Flight(rec)

    def broken(*_call: Any) -> None:
        raise RuntimeError("a recorder bug")

    f.watch.connect(observe=broken)
    f.heartbeat("LOITER", armed=False)
    assert f.sup.seen_link


def test_a_heartbeat_read_otherwise_than_its_fields_say_is_found(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """A reading whose mode is not what its heartbeat's custom mode says (the link's decoding
    at the time of the flight, or a record altered): named with its seq and the fields."""
    path, _rec, _f = recorded(tmp_path / "rec")
    recs = steps(path)
    seq = seq_of(recs, lambda r: r["reading"]["type"] == "HeartbeatSeen" and r["reading"]["fields"]["mode"] == "OFFBOARD")

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        if r["seq"] != seq:
            return r
        before, flight, reading, now, after, outputs = replay_autopilot.loads_step(r["pickle"])
        return with_values(r, before, flight, replace(reading, mode="POSCTL"), now, after, outputs)

    code, out = run(rewrite(path, tmp_path / "misread.mcap", edit, topic=TOPIC), capsys)
    assert code == 1, out
    base, main, sub = mavutil.px4_map["OFFBOARD"]
    assert (f"first difference: seq {seq} HeartbeatSeen(autopilot='px4', mode='POSCTL'" in line(out)
            and f"(MAV_AUTOPILOT 12, MAV_TYPE 2, base_mode {base | 128}, custom_mode {(main << 16) | (sub << 24)}) "
            "reads as px4 'OFFBOARD' armed, recorded px4 'POSCTL' armed" in line(out)), line(out)
    beats = sum(r["reading"]["type"] == "HeartbeatSeen" for r in recs)
    assert f"heartbeats: {beats - 1} of {beats} read again alike" in out


def test_todays_decoding_of_a_recorded_heartbeat_is_checked(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """Replay reads each recorded heartbeat with today's code: a decoding that changed (here PX4's
    AUTO.LOITER sub-mode no longer known) makes the flight's recorded readings differ."""
    path, _rec, _f = recorded(tmp_path / "rec")
    from companion.wire import vehicle

    real = vehicle.decode_mode

    def changed(autopilot: str | None, mav_type: int, base_mode: int, custom_mode: int) -> str:
        name = real(autopilot, mav_type, base_mode, custom_mode)
        return "AUTO" if name == "LOITER" else name

    monkeypatch.setattr(vehicle, "decode_mode", changed)
    code, out = run(path, capsys)
    assert code == 1, out
    assert "first difference: seq 1 HeartbeatSeen(autopilot='px4', mode='LOITER'" in line(out)
    assert "reads as px4 'AUTO' disarmed, recorded px4 'LOITER' disarmed" in line(out)
