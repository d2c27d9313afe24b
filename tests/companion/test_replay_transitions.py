"""Replay of the supervisor's transitions: a Supervisor driven through a flight, recorded by a
real Recorder into a real MCAP file, replays (exit 0); a changed state, a removed record, a
record the recorder dropped, a state replaced outside `handle` are each found and named by
their `seq` (exit 1); a transition record cannot make replay load anything but the
supervisor's own types."""

from __future__ import annotations

import base64
import json
import os
import pickle
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import jsonschema
import pytest
from mcap.reader import make_reader
from mcap.writer import Writer
from recorder_support import config

from companion import channels as ch
from companion import replay, replay_cli
from companion.flight import FlightState, State
from companion.recorder import Recorder
from companion.supervisor import (
    Announce,
    Armed,
    ArmRequested,
    Braking,
    ControlTaken,
    Disarmed,
    Event,
    GroundLearnt,
    Heartbeat,
    LandedStateReport,
    LandRequested,
    MissionComplete,
    MissionStarted,
    ModeReport,
    ReplanFlown,
    StoppedAfterBraking,
    Supervisor,
    TakeoffBegan,
    TakingControl,
    TookOff,
)

TOPIC = "/supervisor/transition"

# arm, take off, fly a mission with a brake and a replan, land, disarm; then a pilot takeover
# of a second flight: every kind of action (Announce, Release, Say), state changes and calls
# that change nothing
FLIGHT: list[Event] = [
    Heartbeat(), GroundLearnt(0.25), Disarmed("POSCTL", False), Heartbeat(), GroundLearnt(0.125),
    ControlTaken(), TakingControl("arm command: taking control"), ArmRequested(), Armed("OFFBOARD"),
    ModeReport(True, "OFFBOARD", False), TakeoffBegan("taking off to 1.50 m"), LandedStateReport(True, False),
    TookOff("airborne at 1.50 m: holding"), MissionStarted("m1"), ModeReport(True, "OFFBOARD", False),
    Braking("pop-up obstacle"), StoppedAfterBraking(), ReplanFlown("around the pop-up"), MissionComplete("m1"),
    LandRequested(), LandedStateReport(False, True), Disarmed("AUTO.LAND", False),
    ControlTaken(), TakingControl("arm command"), ArmRequested(), Armed("OFFBOARD"),
    ModeReport(False, "POSCTL", False), Heartbeat(),
]


def drive(sup: Supervisor, events: list[Event], rec: Recorder | None = None) -> None:
    """Each event handled; with `rec`, once its writer has taken what was queued (a small queue
    must not overflow here: the drops a test wants are made on purpose)."""
    for e in events:
        deadline = time.monotonic() + 10
        while rec is not None and rec.stats()["queued"] and time.monotonic() < deadline:
            time.sleep(0.001)
        sup.handle(e)


def recorded(tmp_path: Path, events: list[Event] = FLIGHT, queue: int = 4096,
             before_open: list[Event] | None = None,
             meddle: Callable[[Supervisor], None] | None = None) -> tuple[Path, list[tuple[Any, ...]], Recorder]:
    """A Supervisor wired to a real Recorder as the service wires it; `before_open`: events
    handled before the writer thread starts (they wait in the queue, or are dropped); `meddle`:
    run halfway through `events`. Returns the file, what the observer was shown, the recorder."""
    rec = Recorder(config(tmp_path, queue=queue))
    sup = Supervisor()
    shown: list[tuple[Any, ...]] = []

    def observe(*call: Any) -> None:
        shown.append(call)
        rec.transition(*call)

    sup.connect(observe=observe)
    drive(sup, before_open or [])
    rec.open()
    half = len(events) // 2
    drive(sup, events[:half], rec)
    if meddle is not None:
        meddle(sup)
    drive(sup, events[half:], rec)
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    return path, shown, rec


def transition_records(path: Path) -> list[dict[str, Any]]:
    with open(path, "rb") as fh:
        return [json.loads(m.data) for _s, _c, m in make_reader(fh).iter_messages(topics=[TOPIC])]


def rewrite(src: Path, dst: Path, edit: Callable[[dict[str, Any]], dict[str, Any] | None] = lambda r: r,
            meta: Callable[[str, dict[str, str]], dict[str, str]] = lambda _n, m: m, topic: str = TOPIC) -> Path:
    """`src` written again with the `mcap` writer, each record on `topic` (the transitions by
    default) through `edit` (None: left out) and each metadata record through `meta`: a file
    altered after the flight."""
    with open(src, "rb") as fh:
        reader = make_reader(fh)
        metadata = [(m.name, dict(m.metadata)) for m in reader.iter_metadata()]
        messages = list(reader.iter_messages())
    with open(dst, "wb") as out:
        w = Writer(out)
        w.start()
        schemas: dict[int, int] = {}
        chans: dict[str, int] = {}
        for schema, channel, m in messages:
            assert schema is not None  # every channel of ours has one
            if channel.topic not in chans:
                if schema.id not in schemas:
                    schemas[schema.id] = w.register_schema(schema.name, schema.encoding, schema.data)
                chans[channel.topic] = w.register_channel(channel.topic, channel.message_encoding, schemas[schema.id])
            data = m.data
            if channel.topic == topic:
                rec = edit(json.loads(data))
                if rec is None:
                    continue
                data = json.dumps(rec).encode()
            w.add_message(chans[channel.topic], log_time=m.log_time, data=data, publish_time=m.publish_time)
        for name, md in metadata:
            w.add_metadata(name, meta(name, md))
        w.finish()  # type: ignore[no-untyped-call]  # mcap's Writer.finish has no annotations
    return dst


def with_values(rec: dict[str, Any], before: Any, event: Any, after: Any, actions: Any) -> dict[str, Any]:
    """`rec` holding these values, JSON and pickle alike (as a recorder would have written them)."""
    return {**rec, **json.loads(ch.dumps(ch.transition_fields(before, event, after, actions))),
            "pickle": base64.b64encode(pickle.dumps((before, event, after, actions), protocol=5)).decode()}


def run(path: Path, capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    code = replay_cli.main([str(path), *args])
    return code, capsys.readouterr().out


def test_every_handle_call_is_recorded_in_order_and_replays(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, shown, rec = recorded(tmp_path)
    recs = transition_records(path)
    assert len(shown) == len(FLIGHT) and rec.dropped == {}
    assert [r["seq"] for r in recs] == list(range(1, len(FLIGHT) + 1))
    assert [r["event"]["type"] for r in recs] == [type(e).__name__ for e in FLIGHT]
    # the readable part says what the observer was shown
    for r, (before, event, after, actions) in zip(recs, shown, strict=True):
        assert r["before"]["state"] == before.state.value and r["after"]["state"] == after.state.value
        assert r["event"]["fields"] == json.loads(json.dumps(ch.transition_fields(before, event, after, actions)["event"]["fields"]))
        assert [a["type"] for a in r["actions"]] == [type(a).__name__ for a in actions]
    assert recs[-2]["after"]["state"] == "PILOT" and [a["type"] for a in recs[-2]["actions"]] == [
        "Release", "Announce", "Say"]
    assert recs[1]["after"]["ground_z"] == 0.25
    # every record validates against its channel's schema, which the file carries
    with open(path, "rb") as fh:
        (schema, channel, _m), *_ = make_reader(fh).iter_messages(topics=[TOPIC])
    assert schema is not None and (schema.name, schema.encoding, channel.message_encoding) == ("bezier.SupervisorTransition", "jsonschema",
                                                                        "json")
    for r in recs:
        jsonschema.validate(r, json.loads(schema.data))
    code, out = run(path, capsys)
    assert code == 0, out
    assert f"transitions: {len(FLIGHT)} of {len(FLIGHT)} reproduced" in out
    assert "plans: none recorded" in out


def test_a_changed_state_after_is_found_with_its_seq_and_field(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    path, _shown, _rec = recorded(tmp_path / "rec")
    seq = 1 + next(i for i, e in enumerate(FLIGHT) if isinstance(e, StoppedAfterBraking))

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        if r["seq"] != seq:
            return r
        before, event, after, actions = replay.loads_transition(r["pickle"])
        assert after.state is State.HOLDING
        return with_values(r, before, event, replace(after, state=State.STREAMING), actions)

    code, out = run(rewrite(path, tmp_path / "changed.mcap", edit), capsys)
    assert code == 1, out
    line = next(ln for ln in out.splitlines() if ln.startswith("transitions:"))
    assert f"first difference: seq {seq} StoppedAfterBraking()" in line
    assert "after.state: recorded <State.STREAMING" in line and "replayed <State.HOLDING" in line
    assert f"transitions: {len(FLIGHT) - 2} of {len(FLIGHT)} reproduced" in line  # and the next one's chain


def test_an_action_changed_is_found(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _shown, _rec = recorded(tmp_path / "rec")
    seq = 1 + FLIGHT.index(MissionStarted("m1"))

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        if r["seq"] != seq:
            return r
        before, event, after, (announce,) = replay.loads_transition(r["pickle"])
        return with_values(r, before, event, after, (replace(announce, reason="flying mission m2"),))

    code, out = run(rewrite(path, tmp_path / "changed.mcap", edit), capsys)
    assert code == 1
    assert f"seq {seq} MissionStarted(mission_id='m1'): actions[0].reason: recorded 'flying mission m2'" in out


def test_a_readable_part_that_is_not_the_pickled_value_is_a_difference(tmp_path: Path,
                                                                       capsys: pytest.CaptureFixture[str]) -> None:
    path, _shown, _rec = recorded(tmp_path / "rec")

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "after": {**r["after"], "state": "HOLDING"}} if r["seq"] == 3 else r

    code, out = run(rewrite(path, tmp_path / "json.mcap", edit), capsys)
    assert code == 1 and "seq 3 Disarmed(mode='POSCTL', stalled=False): the record's after (JSON)" in out


def test_a_removed_record_is_a_gap_named_by_its_seq(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _shown, _rec = recorded(tmp_path / "rec")
    seq = 1 + FLIGHT.index(LandedStateReport(True, False))  # it makes the vehicle airborne
    code, out = run(rewrite(path, tmp_path / "removed.mcap", lambda r: None if r["seq"] == seq else r), capsys)
    assert code == 1, out
    assert (f"transitions: {len(FLIGHT) - 1} of {len(FLIGHT)} reproduced; first difference: seq {seq} missing "
            "(1 record: dropped by the recorder, or removed)") in out


def test_records_the_recorder_dropped_are_counted_and_the_gap_named(tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """A real drop: 10 calls before the writer thread starts, into a queue of 4 (the tap never
    waits: a blocking put would hang here); 5 to 10 are dropped and counted."""
    early: list[Event] = [Heartbeat(), GroundLearnt(0.0)] * 5
    path, shown, rec = recorded(tmp_path, queue=4, before_open=early)
    assert rec.dropped == {"transition": 6}
    recs = transition_records(path)
    assert len(shown) == len(early) + len(FLIGHT) and len(recs) == len(shown) - 6
    meta = replay.recorded_metadata(str(path))
    assert json.loads(meta["recorder"]["dropped"]) == {"transition": 6}
    code, out = run(path, capsys, "--keep-going")
    assert code == 1, out
    n = len(shown)
    assert f"transitions: {n - 6} of {n} reproduced; first difference: seq 5 to 10 missing (6 records" in out
    assert "also: the recorder dropped 6 transition records in this run" in out


def test_a_dropped_count_without_a_gap_is_still_a_difference(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    """The last records dropped leave no gap behind them: the count in the file says so."""
    path, _shown, _rec = recorded(tmp_path / "rec")

    def meta(name: str, md: dict[str, str]) -> dict[str, str]:
        return {**md, "dropped": json.dumps({"transition": 1})} if name == "recorder" else md

    code, out = run(rewrite(path, tmp_path / "dropped.mcap", meta=meta), capsys)
    assert code == 1
    assert (f"transitions: {len(FLIGHT)} of {len(FLIGHT)} reproduced; first difference: the recorder dropped 1 "
            "transition record in this run") in out


def test_a_state_replaced_outside_handle_breaks_the_chain(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Nothing edited after the flight: the supervisor's state was written around `handle`
    (what the chain check is for), and every record on its own replays."""
    def meddle(sup: Supervisor) -> None:
        sup._now = replace(sup.value, airborne=not sup.value.airborne)

    path, _shown, _rec = recorded(tmp_path, meddle=meddle)
    seq = len(FLIGHT) // 2 + 1
    code, out = run(path, capsys)
    assert code == 1, out
    assert (f"first difference: seq {seq} {FLIGHT[seq - 1]!r}: does not start where seq {seq - 1} ended "
            f"(before.airborne: seq {seq - 1} ended in") in out
    assert f"transitions: {len(FLIGHT) - 1} of {len(FLIGHT)} reproduced" in out


def test_the_time_range_selects_transitions_too(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _shown, _rec = recorded(tmp_path)
    code, out = run(path, capsys, "--from", "3600")
    assert code == 2 and "transitions: none recorded" in out  # nothing an hour in: nothing to replay


class _Evil:
    def __reduce__(self) -> Any:
        return (os.system, ("echo pwned > pwned.txt",))


def test_a_transition_record_cannot_name_anything_else(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    path, _shown, _rec = recorded(tmp_path / "rec")

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "pickle": base64.b64encode(pickle.dumps((FlightState(), _Evil(), FlightState(), ()))).decode()}

    bad = rewrite(path, tmp_path / "evil.mcap", edit)
    assert replay_cli.main([str(bad)]) == 2
    assert "replay does not load posix.system" in capsys.readouterr().err
    assert not (tmp_path / "pwned.txt").exists()
    # a planner function is allowed in a plan record, not in a transition record
    with pytest.raises(pickle.UnpicklingError):
        from companion.mission import start_mission
        replay.loads_transition(base64.b64encode(pickle.dumps(start_mission)).decode())


def test_an_observer_that_fails_never_keeps_the_actions_from_running() -> None:
    sup = Supervisor()
    released: list[bool] = []
    announced: list[Announce] = []

    def broken(*_call: Any) -> None:
        raise RuntimeError("a recorder bug")

    sup.connect(observe=broken, release=lambda: released.append(True), announce=announced.append)
    drive(sup, [Heartbeat(), ControlTaken(), TakingControl("arm"), Armed("OFFBOARD"),
                ModeReport(False, "POSCTL", False)])
    assert sup.state is State.PILOT and released == [True] and [a.dst for a in announced] == [
        State.ARMING, State.READY, State.PILOT]
