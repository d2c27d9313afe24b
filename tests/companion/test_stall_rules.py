"""The stall watch's one rule (companion.stall_rules.stall_step) and its replay.

The rule decides as the watch's loop did before it was one pure function (an oracle copy of that
code, on generated beat sequences); a real StallWatch, its loop stalled for real and its sender's
latch set as a stalled setpoint thread sets it, shown to a real Recorder, writes its calls into a
real MCAP file, which replay runs again alike (exit 0); a changed action, a replaced state, a first
record not from a fresh watch, a removed record, a stall not dealt with and today's rule changed
are each named by their seq (exit 1); a record naming another class is refused (exit 2)."""

from __future__ import annotations

import asyncio
import json
import time
from dataclasses import replace
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from recorder_support import config, schema_checked
from test_replay_transitions import rewrite

from companion import replay_cli, stall_rules
from companion.recorder import Recorder
from companion.setpoints import Liveness
from companion.stall_rules import (
    STALL_HOLD_WITHIN,
    Beat,
    Settled,
    Stalled,
    StallRules,
    StallState,
    stall_step,
)
from companion.stalls import StallWatch

TOPIC = "/stalls/step"
STATES = ("IDLE", "HOLDING", "STREAMING", "BRAKING", "FAILSAFE")


def _old(limit: float, first: str, beats: list[tuple[float, Any, float, bool, str, str]]) -> list[tuple[Any, ...]]:
    """The loop's decisions as they were before the rule (verbatim but for the I/O): per stall,
    the reason, the reaction, the state before and the event's fields; the oracle."""
    was, out = first, []
    for gap, withheld, silence, controlling, state, state_after in beats:
        if gap <= limit and withheld is None:
            was = state  # as it was before any stall
            continue
        what = "the setpoint thread" if withheld is not None and withheld[1] == "thread" else "its event loop"
        stall = max(gap, withheld[2] if withheld is not None else 0.0)
        reason = f"the companion stalled ({what} did not run for {stall * 1000:.0f} ms)"
        if not controlling:
            reaction = "not in control"
        elif withheld is not None and silence >= STALL_HOLD_WITHIN:
            reaction = "released control"
        else:
            reaction = "hold"
        out.append((reason, reaction, was, what, stall, withheld is not None, silence))
        was = state_after
    return out


beats = st.lists(st.tuples(
    st.floats(0.0, 3.0),
    st.one_of(st.none(), st.tuples(st.floats(0.0, 100.0), st.sampled_from(("loop", "thread")), st.floats(0.0, 3.0))),
    st.floats(0.0, 2.0), st.booleans(), st.sampled_from(STATES), st.sampled_from(STATES)), max_size=40)


@settings(max_examples=300, deadline=None)
@given(st.floats(0.05, 3.0), st.sampled_from(STATES), beats)
def test_the_rule_decides_as_the_loop_did(limit: float, first: str, seq: list[tuple[Any, ...]]) -> None:
    rules = StallRules(limit)
    state, _ = stall_step(rules, StallState(), Settled(first))
    got = []
    for gap, withheld, silence, controlling, now, after in seq:
        beat = Beat(gap, None if withheld is None else withheld[1], 0.0 if withheld is None else withheld[2], silence,
                    controlling, now)
        state, action = stall_step(rules, state, beat)
        if isinstance(action, Stalled):
            reaction = {"none": "not in control", "release": "released control", "hold": "hold"}[action.reaction]
            got.append((action.reason, reaction, action.was, action.what, action.stall, action.withheld,
                        action.silence))
            state, _ = stall_step(rules, state, Settled(after))
    assert got == _old(limit, first, seq)


class _Report:
    def __init__(self) -> None:
        self.events: list[tuple[str, str, dict[str, Any]]] = []

    def event(self, kind: str, message: str, **extra: Any) -> None:
        self.events.append((kind, message, extra))


def _watched(tmp_path: Path, queue: int = 4096) -> tuple[Path, _Report, list[str]]:
    """A real StallWatch (its collaborators stand-ins that note what it asks) shown to a real
    Recorder: flying, the loop held up 0.4 s past a 0.25 s limit (hold); then the setpoint
    thread's latch, 0.6 s after the last setpoint (release control); then not in control."""
    base = config(tmp_path, queue=queue)
    cfg = replace(base, setpoints=replace(base.setpoints, loop_stall_limit=0.25))
    asked: list[str] = []
    flight = SimpleNamespace(state=SimpleNamespace(value="STREAMING"), controlling=True)

    def hold(reason: str) -> str:
        asked.append(f"hold: {reason}")
        flight.state.value = "HOLDING"
        return "holding"

    def release(reason: str) -> None:
        asked.append(f"release: {reason}")
        flight.state.value, flight.controlling = "FAILSAFE", False

    rec = Recorder(cfg)
    report = _Report()
    watch = StallWatch.__new__(StallWatch)
    watch.cfg, watch.stop, watch.report = cfg, asyncio.Event(), report
    watch.link = SimpleNamespace(link_ok=lambda: True, state=SimpleNamespace(mode="OFFBOARD"))
    watch.flight = flight  # type: ignore[assignment]
    watch.handover = SimpleNamespace(hold_after_stall=hold, after_stall=release)  # type: ignore[assignment]
    watch.liveness = Liveness(cfg.setpoints.loop_stall_limit)
    watch.observe = rec.stall_step
    rec.open()

    async def main() -> None:
        task = asyncio.create_task(watch.loop_liveness())
        await asyncio.sleep(0.1)
        time.sleep(0.4)  # the loop held up
        await asyncio.sleep(0.1)
        live = watch.liveness
        live.check(time.monotonic(), 0.0)  # a setpoint leaves
        flight.state.value = "STREAMING"
        await asyncio.sleep(0.6)
        assert not live.check(time.monotonic(), 0.7)  # the sender woke 0.7 s late: it latches
        await asyncio.sleep(0.1)
        live.check(time.monotonic(), 0.0)
        time.sleep(0.4)  # the loop held up again, now out of control
        await asyncio.sleep(0.1)
        watch.stop.set()
        await task

    asyncio.run(main())
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    return path, report, asked


@pytest.fixture(scope="module")
def watched(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, _Report, list[str]]:
    return _watched(tmp_path_factory.mktemp("stalls"))


def run(path: Path, capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    code = replay_cli.main([str(path), *args])
    return code, next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("stalls:"))


def test_each_stall_is_decided_recorded_and_replayed_alike(watched: tuple[Path, _Report, list[str]],
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    path, report, asked = watched
    stalls = [e for e in report.events if e[0] == "stalled"]
    assert [e[2]["stalled"] for e in stalls] == ["event_loop", "the_setpoint_thread", "event_loop"], stalls
    assert [e[2]["previous_state"] for e in stalls] == ["STREAMING", "STREAMING", "FAILSAFE"]
    assert stalls[0][2]["stall_ms"] >= 380 and not stalls[0][2]["setpoints_withheld"]
    assert stalls[1][2]["setpoints_withheld"] and stalls[1][2]["silence_ms"] >= 500
    assert "holding" in stalls[0][1] and "released control" in stalls[1][1] and "not in control" in stalls[2][1]
    assert [a.split(":")[0] for a in asked] == ["hold", "release"]
    recs = schema_checked(path, TOPIC, "bezier.StallStep")
    assert [r["seq"] for r in recs] == list(range(1, len(recs) + 1))
    kinds = [(r["observation"]["type"], r["action"]["type"]) for r in recs]
    assert kinds[0] == ("Settled", "Quiet") and kinds.count(("Beat", "Stalled")) == 3
    # each stall dealt with before the next beat: its Settled follows it
    for i, k in enumerate(kinds):
        if k[1] == "Stalled":
            assert kinds[i + 1][0] == "Settled"
    assert run(path, capsys) == (0, f"stalls: {len(recs)} of {len(recs)} reproduced (3 stalls: 1 held, 1 released "
                                    "control, 1 not in control)")


def _first(path: Path, kind: str) -> int:
    recs = [json.loads(r) for r in _raw(path)]
    return next(r["seq"] for r in recs if r["action"]["type"] == kind)


def _raw(path: Path) -> list[str]:
    from mcap.reader import make_reader

    with path.open("rb") as f:
        return [m.data.decode() for _s, _c, m in make_reader(f).iter_messages(topics=[TOPIC])]


def test_a_changed_action_is_named(tmp_path: Path, watched: tuple[Path, _Report, list[str]],
                                   capsys: pytest.CaptureFixture[str]) -> None:
    path = watched[0]
    at = _first(path, "Stalled")

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        if r["seq"] != at:
            return r
        return {**r, "action": {**r["action"], "fields": {**r["action"]["fields"], "reaction": "release"}}}

    code, line = run(rewrite(path, tmp_path / "action.mcap", edit, topic=TOPIC), capsys)
    assert code == 1 and f"first difference: seq {at} Beat(" in line and "action" in line, line


def test_a_state_replaced_outside_the_rule_and_a_first_record_not_fresh_are_named(
        tmp_path: Path, watched: tuple[Path, _Report, list[str]], capsys: pytest.CaptureFixture[str]) -> None:
    path = watched[0]
    at = _first(path, "Stalled")

    def replaced(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "before": {"was": "LANDING"}} if r["seq"] == at else r

    code, line = run(rewrite(path, tmp_path / "chain.mcap", replaced, topic=TOPIC), capsys)
    assert code == 1 and f"seq {at} Beat(" in line and f"does not start where seq {at - 1} ended" in line, line

    def first(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "before": {"was": "STREAMING"}} if r["seq"] == 1 else r

    code, line = run(rewrite(path, tmp_path / "first.mcap", first, topic=TOPIC), capsys)
    assert code == 1 and "seq 1 Settled(" in line and "the state a watch starts with" in line, line


def test_a_removed_record_is_a_gap_and_a_stall_not_dealt_with_is_named(
        tmp_path: Path, watched: tuple[Path, _Report, list[str]], capsys: pytest.CaptureFixture[str]) -> None:
    path = watched[0]
    at = _first(path, "Stalled")
    code, line = run(rewrite(path, tmp_path / "gap.mcap", lambda r: None if r["seq"] == at + 1 else r,
                             topic=TOPIC), capsys)
    assert code == 1 and f"seq {at + 1} missing (1 record" in line, line

    def as_beat(r: dict[str, Any]) -> dict[str, Any]:
        if r["seq"] != at + 1:
            return r
        state = r["observation"]["fields"]["state"]
        beat = {"gap": 0.02, "withheld_by": None, "withheld_stall": 0.0, "silence": 0.02, "controlling": True,
                "state": state}
        return {**r, "observation": {"type": "Beat", "fields": beat}}

    code = replay_cli.main([str(rewrite(path, tmp_path / "unsettled.mcap", as_beat, topic=TOPIC)), "--keep-going"])
    out = capsys.readouterr().out
    assert code == 1 and f"the stall at seq {at} was not dealt with (no Settled) before this beat" in out, out


def test_records_the_recorder_dropped_are_counted(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A queue of 2 before the writer starts: the calls past it are dropped, counted, named."""
    cfg = config(tmp_path, queue=2)
    rec = Recorder(cfg)
    rules, state = StallRules(1.5), StallState()
    for value in STATES:
        before = state
        state, action = stall_step(rules, before, Settled(value))
        rec.stall_step(rules, before, Settled(value), state, action)
    rec.open()
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    code, line = run(path, capsys)
    assert code == 1 and line == ("stalls: 2 of 2 reproduced; first difference: the recorder dropped 3 stall step "
                                  "records in this run (its queue was full): the chain is not checkable across them")


def test_todays_rule_changed_is_a_difference(watched: tuple[Path, _Report, list[str]],
                                             capsys: pytest.CaptureFixture[str],
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(stall_rules, "LOOP", "the event loop")
    code, line = run(watched[0], capsys)
    assert code == 1 and "Beat(" in line and "action" in line, line


def test_a_record_naming_another_class_is_refused(tmp_path: Path, watched: tuple[Path, _Report, list[str]],
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "observation": {"type": "Popen", "fields": {"args": ["true"]}}} if r["seq"] == 1 else r

    code = replay_cli.main([str(rewrite(watched[0], tmp_path / "foreign.mcap", edit, topic=TOPIC))])
    err = capsys.readouterr().err
    assert code == 2 and "'Popen' is not a stall observation or action" in err, err
