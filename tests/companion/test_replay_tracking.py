"""Replay of the tracking error's steps: a Tracking, a Supervisor and a Reporter wired to a real
Recorder as the service wires them, fed a flight's position samples (the errors scripted: the
control and the link are stand-ins, the brake's hold makes the Braking transitions the brakes
make), recorded into a real MCAP file; replay runs every step again (exit 0) and ties the
tracking brake to its Braking transition; a changed state, a removed step, a brake no step
asked for and steps the recorder dropped are each named by their seq (exit 1); a file without
the channel says so; a record read back names only the rules' own classes."""

from __future__ import annotations

import asyncio
import json
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from recorder_support import BrakingNavigator, ScriptedControl, TrackingLink, config, schema_checked
from test_replay_transitions import rewrite, transition_records

from companion import replay, replay_cli
from companion.config import PlannerConfig
from companion.recorder import Recorder
from companion.report import Reporter
from companion.supervisor import (
    Armed,
    ArmRequested,
    ControlTaken,
    GroundLearnt,
    Heartbeat,
    LandRequested,
    MissionStarted,
    Supervisor,
    TakeoffBegan,
    TakingControl,
    TookOff,
)
from companion.tracking import TRACKING_SAMPLES, TRACKING_WINDOW, Tracking

TOPIC = "/tracking/step"
ALLOWANCE = 0.5
UP = [Heartbeat(), GroundLearnt(0.0), ControlTaken(), TakingControl("arm command"), ArmRequested(),
      Armed("OFFBOARD"), TakeoffBegan("taking off to 1.50 m"), TookOff("airborne at 1.50 m: holding"),
      MissionStarted("m1")]


class Rig:
    def __init__(self, rec: Recorder) -> None:
        self.rec = rec
        self.writing = False
        self.sup = Supervisor()
        self.sup.connect(observe=rec.transition)
        self.events: list[dict[str, Any]] = []
        self.report = Reporter(self.sup, publish=lambda _k, body: self.events.append(body))
        self.control = ScriptedControl()
        self.link = TrackingLink()
        self.nav = BrakingNavigator(self.sup)
        self.tracking = Tracking(rec.cfg, self.sup, self.control, self.link, self.nav, self.report)  # type: ignore[arg-type]
        self.tracking.connect(observe=rec.tracking_step)
        self.calls = 0

    def settle(self) -> None:
        """A small queue must not overflow here: the drops a test wants are made on purpose."""
        if self.rec.cfg.recording.queue > 1000:
            return
        deadline = time.monotonic() + 10
        while self.writing and self.rec.stats()["queued"] and time.monotonic() < deadline:
            time.sleep(0.001)

    async def samples(self, *errors: float) -> None:
        for e in errors:
            self.settle()
            self.control.error = e
            self.calls += 1
            self.tracking.check_tracking(time.monotonic())
            await asyncio.sleep(0)

    def handle(self, *events: Any) -> None:
        for e in events:
            self.settle()
            self.sup.handle(e)


async def fly(r: Rig, meddle: Callable[[Rig], Any] | None = None, up: bool = True) -> None:
    """On the ground, up (unless `up` already), a mission flown near the allowance (the margin
    warning), an excursion over it (the brake; held, it goes on: said once), back, landed."""
    if up:
        await r.samples(0.0, 0.0)  # not controlling yet: nothing recorded
        r.handle(*UP)
    await r.samples(*[0.3] * (TRACKING_WINDOW // 3 + 5))
    if meddle is not None:
        await meddle(r)
    await r.samples(*[0.9] * (TRACKING_SAMPLES + 4))
    await asyncio.sleep(0.05)  # the stop flown
    await r.samples(*[0.1] * 5)
    r.handle(LandRequested())
    await r.samples(0.1, 0.1)


def recorded(tmp_path: Path, queue: int = 4096, early: int = 0,
             meddle: Callable[[Rig], Any] | None = None, **rec: Any) -> tuple[Path, Recorder, Rig]:
    """`early`: the vehicle up and as many samples before the writer thread starts (they wait in
    the queue, or are dropped); `rec`: more of [recording]."""
    cfg = config(tmp_path, queue=queue, **rec)
    rec = Recorder(replace(cfg, planner=replace(cfg.planner, tracking_allowance=ALLOWANCE)))
    rig = Rig(rec)

    async def go() -> None:
        if early:
            rig.handle(*UP)
            await rig.samples(*[0.05] * early)
        rec.open()
        rig.writing = True
        await fly(rig, meddle, up=not early)

    asyncio.run(go())
    rec.close()
    path = min(tmp_path.glob("*.mcap"), key=lambda p: len(p.name))  # the first part: no -001
    return path, rec, rig


@pytest.fixture(scope="module")
def flown(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """One recorded flight for the tests that alter it afterwards."""
    path, _rec, _rig = recorded(tmp_path_factory.mktemp("flight"))
    return path


def steps(path: Path) -> list[dict[str, Any]]:
    with open(path, "rb") as fh:
        return [json.loads(m.data) for _s, _c, m in make_reader(fh).iter_messages(topics=[TOPIC])]


def run(path: Path, capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    code = replay_cli.main([str(path), *args])
    return code, capsys.readouterr().out


def line(out: str) -> str:
    return next(ln for ln in out.splitlines() if ln.startswith("tracking steps:"))


def braked(recs: list[dict[str, Any]]) -> int:
    return int(next(r for r in recs if any(o["type"] == "Brake" for o in r["outputs"]))["seq"])


def test_every_step_is_recorded_and_replays_with_its_brake_a_braking_transition(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, rec, rig = recorded(tmp_path)
    recs = steps(path)
    assert rec.dropped == {} and [r["seq"] for r in recs] == list(range(1, len(recs) + 1))
    # the calls on the ground and the second one landing changed nothing and are not recorded;
    # every one in the air, and the first landing (the window forgotten), is
    assert len(recs) == rig.calls - 3
    outputs = [o["type"] for r in recs for o in r["outputs"]]
    assert outputs == ["MarginEvent", "TrackingEvent", "Brake"]
    said = [e["type"] for e in rig.events if e["type"] in ("tracking", "tracking_margin", "braking")]
    assert said == ["tracking_margin", "tracking"]  # the braking event is the brakes', not this stand-in's
    assert recs[0]["window"] is None and recs[-1]["after"]["errors"] == 0  # landed: the window emptied
    assert schema_checked(path, TOPIC, "bezier.TrackingStep") == recs
    code, out = run(path, capsys)
    assert code == 0, out
    assert f"tracking steps: {len(recs)} of {len(recs)} reproduced (1 brake, 1 followed by its Braking transition)" \
        in out.splitlines()
    # from the middle of the flight: the records before the range rebuild the window
    with open(path, "rb") as fh:
        times = [m.log_time for _s, _c, m in make_reader(fh).iter_messages()]
        fh.seek(0)
        late = [m.log_time for _s, _c, m in make_reader(fh).iter_messages(topics=[TOPIC])][TRACKING_WINDOW // 3 + 2]
    code, out = run(path, capsys, "--from", str((late - times[0]) / 1e9))
    assert code == 0, out
    n = len(recs) - (TRACKING_WINDOW // 3 + 2)
    assert f"tracking steps: {n} of {n} reproduced (1 brake, 1 followed by its Braking transition)" in out


def test_a_changed_state_after_is_found_with_its_seq_and_field(tmp_path: Path, flown: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    path = flown
    recs = steps(path)
    seq = braked(recs) - 1

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "after": {**r["after"], "over": r["after"]["over"] + 1}} if r["seq"] == seq else r

    code, out = run(rewrite(path, tmp_path / "changed.mcap", edit, topic=TOPIC), capsys)
    assert code == 1, out
    said = line(out)
    assert f"first difference: seq {seq} TrackingSample(error=0.9" in said and "after.over: recorded 3, replayed 2" in said
    # and the next one (the brake) no longer starts where this one, as recorded, ended
    assert f"tracking steps: {len(recs) - 2} of {len(recs)} reproduced" in said


def test_a_removed_step_is_a_gap_and_its_brake_asked_for_by_no_step(tmp_path: Path, flown: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    path = flown
    recs = steps(path)
    seq = braked(recs)
    code, out = run(rewrite(path, tmp_path / "removed.mcap", lambda r: None if r["seq"] == seq else r, topic=TOPIC),
                    capsys, "--keep-going")
    assert code == 1, out
    assert f"first difference: seq {seq} missing (1 record: dropped by the recorder, or removed)" in line(out)
    assert "Braking(reason='tracking error 0.90 m > [planner] tracking_allowance 0.50 m') was asked for by no " \
           "recorded tracking step" in out


def test_a_tracking_brake_no_step_asked_for_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Nothing edited after the flight: a hold with a tracking reason asked for by something else
    than the rules; every step on its own replays."""
    async def meddle(r: Rig) -> None:
        await r.nav.hold("tracking error 0.31 m > [planner] tracking_allowance 0.50 m", None)

    path, _rec, _rig = recorded(tmp_path, meddle=meddle)
    code, out = run(path, capsys)
    assert code == 1, out
    said = line(out)
    n = len(steps(path))
    with open(path, "rb") as fh:
        (seq,) = [json.loads(m.data)["seq"] for _s, _c, m in make_reader(fh).iter_messages(
            topics=["/supervisor/transition"]) if "0.31 m" in m.data.decode()]
    assert said == (f"tracking steps: {n} of {n} reproduced; first difference: transition {seq} Braking(reason="
                    "'tracking error 0.31 m > [planner] tracking_allowance 0.50 m') was asked for by no recorded "
                    "tracking step")


def test_steps_the_recorder_dropped_are_counted_and_replay_goes_on_from_the_next(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A real drop: the vehicle up and 8 samples before the writer thread starts, into a queue
    that holds the transitions and 2 of them: 6 dropped and counted under tracking_step; the
    next record holds the window in full, and every record from there replays."""
    path, rec, _rig = recorded(tmp_path, queue=len(UP) + 2, early=8)
    assert rec.dropped == {"tracking_step": 6}
    assert json.loads(replay.recorded_metadata(str(path))["recorder"]["dropped"]) == {"tracking_step": 6}
    recs = steps(path)
    assert recs[2]["seq"] == 9 and recs[2]["window"] == [0.05] * 8  # the keyframe after the gap
    code, out = run(path, capsys, "--keep-going")
    assert code == 1, out
    n = len(recs) + 6
    assert f"tracking steps: {n - 6} of {n} reproduced; first difference: seq 3 to 8 missing (6 records" in line(out)
    assert "also: the recorder dropped 6 tracking step records in this run" in out


def test_each_file_of_a_rotated_recording_replays_from_its_first_step(tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """Files of 6 kB: the flight's steps in several, each after the first starting mid-flight
    with the window of errors in full (no gap in the numbers: the recorder's writer knows)."""
    _path, _rec, _rig = recorded(tmp_path, max_bytes=6_000, keep_bytes=10**9)
    parts = sorted(tmp_path.glob("*.mcap"), key=lambda p: (len(p.name), p.name))
    assert len(parts) >= 3
    firsts = [steps(p)[0] for p in parts if steps(p)]
    assert firsts[0]["window"] is None and any(f["window"] for f in firsts[1:])
    seqs = [r["seq"] for p in parts for r in steps(p)]
    assert seqs == list(range(1, len(seqs) + 1))
    for part in parts:
        n = len(steps(part))
        code, out = run(part, capsys)
        assert (code, line(out).split(" (")[0]) == (0, f"tracking steps: {n} of {n} reproduced"), out


def test_a_file_without_tracking_steps_says_so(tmp_path: Path, flown: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = flown
    code, out = run(rewrite(path, tmp_path / "none.mcap", lambda r: None, topic=TOPIC), capsys)
    assert code == 0, out
    assert "tracking steps: none recorded" in out.splitlines()


def test_a_tracking_step_record_cannot_name_another_class(tmp_path: Path, flown: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """Read back from JSON into the rules' own classes, by name: any other is refused (exit 2)."""
    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "outputs": [{"type": "Braking", "fields": {"reason": "tracking error"}}]} if r["seq"] == 2 else r

    assert replay_cli.main([str(rewrite(flown, tmp_path / "other.mcap", edit, topic=TOPIC))]) == 2
    assert "'Braking' is not a tracking reading or output" in capsys.readouterr().err


def test_an_observer_that_fails_never_keeps_the_vehicle_from_braking(tmp_path: Path) -> None:
    rec = Recorder(replace(config(""), planner=PlannerConfig(tracking_allowance=ALLOWANCE)))
    rig = Rig(rec)

    def broken(*_call: Any) -> None:
        raise RuntimeError("a recorder bug")

    rig.tracking.connect(observe=broken)

    async def go() -> None:
        rig.handle(*UP)
        await rig.samples(*[0.9] * TRACKING_SAMPLES)
        await asyncio.sleep(0.05)

    asyncio.run(go())
    assert rig.sup.state.value == "HOLDING"


def test_the_limit_follows_the_autopilot_linked(tmp_path: Path) -> None:
    """The brake's limit is built once per autopilot, not per sample: a link to another
    autopilot (or the first heartbeat) must still change it."""
    cfg = config(tmp_path)
    rig = Rig(Recorder(replace(cfg, planner=replace(cfg.planner, tracking_allowance="autopilot"))))
    seen: list[tuple[float, str]] = []
    rig.tracking.connect(observe=lambda _b, reading, *_: seen.append((reading.limit, reading.limit_name)))

    async def go() -> None:
        rig.handle(*UP)
        for autopilot in (None, "px4", "ardupilot", "px4"):
            rig.link.state.autopilot = autopilot
            await rig.samples(*[5.0] * 2)  # over any allowance: each sample is a step shown

    asyncio.run(go())
    names = [name for _limit, name in seen]
    assert [limit for limit, _name in seen] == [0.4, 0.4, 1.0, 1.0, 0.4, 0.4, 1.0, 1.0]
    assert "not yet known" in names[0] and "PX4" in names[2] and "ArduPilot" in names[4] and "PX4" in names[6]


def test_a_file_that_starts_while_a_brake_is_planned_ties_its_braking_transition(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Files small enough that one rotates between a brake's step and its Braking transition,
    with another step first in the new file (its reading says the tracking stop still runs):
    that file, replayed alone, ties the transition to the step before it, not a difference."""
    straddled = 0
    # where a file rotates depends on when the writer thread writes: sizes until the case is made
    for size in range(2_500, 9_001, 250):
        if straddled:
            break
        where = tmp_path / str(size)
        where.mkdir()
        recorded(where, max_bytes=size, keep_bytes=10**9)
        for part in sorted(where.glob("*.mcap"), key=lambda p: (len(p.name), p.name)):
            recs = steps(part)
            if not recs:  # a file of other records only (tiny files): nothing of this to replay
                continue
            code, out = run(part, capsys)
            assert code == 0, out
            straddled += recs[0]["reading"]["fields"]["stop_running"] and any(
                "Braking" in json.dumps(t) for t in transition_records(part))
    assert straddled, "no file started between a brake's step and its transition: the case was not made"
