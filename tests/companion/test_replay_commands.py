"""Replay of the operator commands' sequences' decisions: today's `Commands`, in the scripted
world of test_command_rules (an arm denied and the mode restored, a takeoff whose PX4 climb
comes late and is moved later from the hold, a landing, an abort, a disarm), wired to a real
Recorder and a real Supervisor as the service wires them, recorded into a real MCAP file;
replay runs every step again alike (exit 0), each transition a step made being the
/supervisor/transition record it names; a changed state, today's rule changed, a removed record,
records the recorder dropped and a transition record unlike the one the step made are each
named (exit 1)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader
from recorder_support import config, schema_checked
from test_command_rules import _DENIED, _OK, _world
from test_replay_swaps import run
from test_replay_transitions import rewrite

from companion import replay_commands
from companion.command_rules import Begin, CommandRules, CommandState, command_step
from companion.commands import Commands
from companion.control import SWAP_LATE
from companion.recorder import Recorder

TOPIC = "/commands/step"
OPS = [("arm", 1.0, "ground"), ("takeoff", 2.0, "ground"), ("land", 0.0, ""), ("abort", 0.0, ""), ("disarm", 0.0, "")]


def recorded(tmp_path: Path, queue: int = 4096, early: int = 0) -> tuple[Path, Recorder, list[tuple[Any, ...]]]:
    """`early`: as many one-step runs before the writer thread starts (they wait in the queue,
    or are dropped)."""
    rec = Recorder(config(tmp_path, queue=queue))

    def wire(cmds: Commands, flight: Any) -> None:
        flight.connect(observe=rec.transition)
        cmds.observe = rec.command_step
        rules, begin = CommandRules("land"), Begin("px4", True, "POSCTL", 1, 2, "PILOT", False, 0.0)
        for i in range(early):
            rec.command_step(100 + i, 1, rules, CommandState(), begin, *command_step(rules, CommandState(), begin))
        rec.open()

    world = _world("px4", [_OK, _OK, _DENIED, _OK, _OK], OPS, plans=[(True, 0.8, 70.0)], refusals=[SWAP_LATE],
                   holds=[True])
    did = world.run(Commands, wire)
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    return path, rec, did


def steps(path: Path, topic: str = TOPIC) -> list[dict[str, Any]]:
    with open(path, "rb") as fh:
        return [json.loads(m.data) for _s, _c, m in make_reader(fh).iter_messages(topics=[topic])]


def line(out: str) -> str:
    return next(ln for ln in out.splitlines() if ln.startswith("commands:"))


def test_every_step_is_recorded_and_reproduced(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, rec, did = recorded(tmp_path)
    # the world did what the test needs: the arm refused and the mode restored, the late climb moved
    assert ("send", "restore_mode", 81, 7) in did and any(d[0] == "held" for d in did)
    recs = steps(path)
    assert rec.dropped == {} and [r["seq"] for r in recs] == list(range(1, len(recs) + 1))
    runs = sorted({r["call"] for r in recs})
    assert all([r["step"] for r in recs if r["call"] == c] == list(range(1, 1 + sum(r["call"] == c for r in recs)))
               for c in runs)
    sequences = [next(r["rules"]["sequence"] for r in recs if r["call"] == c) for c in runs]
    assert sequences == ["arm", "follow", "outcome", "takeoff", "arm", "follow", "climb", "outcome", "land",
                         "on_ground", "outcome", "abort", "disarm"]
    kinds = [(r["observation"]["type"], r["action"]["type"]) for r in recs]
    assert ("ClimbSwapped", "MoveClimb") in kinds and ("ClimbMoved", "Await") in kinds
    assert schema_checked(path, TOPIC, "bezier.CommandStep") == recs
    code, out = run(path, capsys)
    assert code == 0, out
    ends = [r["action"]["type"] for r in recs if r["action"]["type"] in ("Finish", "Fail")]
    made = sum(r["action"]["type"] in ("Transition", "TakeControl") for r in recs)
    assert made == sum(d[0] == "transition" for d in did)  # every transition of this world is a sequence's
    assert (f"commands: {len(recs)} of {len(recs)} reproduced ({ends.count('Finish')} runs finished, "
            f"{ends.count('Fail')} failed; {made} of {made} transitions found as made)") in out.splitlines()
    assert ends.count("Fail") == 1  # the arm denied


def test_a_changed_state_is_found_with_its_seq(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _rec, _d = recorded(tmp_path / "rec")
    target = next(r for r in steps(path) if r["action"]["type"] == "MoveClimb")

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "after": {**r["after"], "ahead": r["after"]["ahead"] + 1.0}} if r["seq"] == target["seq"] else r

    code, out = run(rewrite(path, tmp_path / "changed.mcap", edit, topic=TOPIC), capsys)
    assert code == 1, out
    said = line(out)
    # the step itself, and the next, which starts where the changed one says it ended
    n = len(steps(path))
    assert said.startswith(f"commands: {n - 2} of {n} reproduced; first difference: seq {target['seq']} (climb, "
                           f"run {target['call']} step {target['step']}) ClimbSwapped("), said
    assert "after.ahead" in said


def test_todays_rule_is_what_runs_again(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """A rule that changed since the flight (here: a late swap is no longer told apart, so the
    climb is not moved later) makes the recorded step differ."""
    path, _rec, _d = recorded(tmp_path / "rec")
    from companion import command_rules

    monkeypatch.setattr(command_rules, "SWAP_LATE", "something else")
    code, out = run(path, capsys)
    assert code == 1, out
    target = next(r for r in steps(path) if r["action"]["type"] == "MoveClimb")
    assert f"first difference: seq {target['seq']} (climb, run {target['call']} step {target['step']}) " \
        "ClimbSwapped(" in line(out)
    assert "action: recorded MoveClimb(" in line(out) or "after." in line(out), line(out)


def test_a_removed_record_is_a_gap(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _rec, _d = recorded(tmp_path / "rec")
    code, out = run(rewrite(path, tmp_path / "removed.mcap", lambda r: None if r["seq"] == 4 else r, topic=TOPIC),
                    capsys)
    assert code == 1, out
    assert line(out).startswith(f"commands: {len(steps(path)) - 1} of {len(steps(path))} reproduced; first "
                                "difference: seq 4 missing (1 record: dropped by the recorder, or removed)")


def test_records_the_recorder_dropped_are_said(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, rec, _d = recorded(tmp_path, queue=1, early=4)
    dropped = rec.dropped.get("command_step", 0)
    assert dropped >= 3  # the first waited in the queue of one (later ones may find it full too)
    kept = [r["seq"] for r in steps(path)]
    assert kept[0] == 1 and 2 not in kept  # the early ones found the queue full (and later ones may have)
    found, recorded_any = replay_commands.replay_file(str(path))
    assert recorded_any and found.differences[-1].startswith(
        f"the recorder dropped {dropped} command step records in this run (its queue was full)")
    code, out = run(path, capsys)
    assert code == 1, out
    first = "seq 2 " if len(kept) > 1 else "the recorder dropped"  # a gap before a record kept, else the count
    assert line(out).startswith("commands: ") and f"first difference: {first}" in line(out)


def test_a_transition_unlike_the_one_the_step_made_is_found(tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    path, _rec, _d = recorded(tmp_path / "rec")
    began = next(r for r in steps(path) if r["action"]["type"] == "Transition"
                 and r["action"]["fields"]["event"] == "TakeoffBegan")
    from companion.supervisor import TakeoffBegan

    def edit(r: dict[str, Any]) -> dict[str, Any] | None:
        return None if r["seq"] == began["transition"] else r

    # the transition left out: the step names one the file does not hold
    code, out = run(rewrite(path, tmp_path / "gone.mcap", edit, topic="/supervisor/transition"), capsys)
    assert code == 1, out
    assert f"seq {began['seq']} (takeoff, run {began['call']} step {began['step']}) Aimed(" in line(out)
    assert f"makes transition {began['transition']}, which the file does not hold" in line(out)
    # the step's reason changed: the transition record is not the event it made
    reason = began["action"]["fields"]["reason"]
    edited = rewrite(path, tmp_path / "reason.mcap", lambda r: {**r, "action": {**r["action"], "fields": {
        **r["action"]["fields"], "reason": reason + "!"}}} if r["seq"] == began["seq"] else r, topic=TOPIC)
    code, out = run(edited, capsys)
    assert code == 1, out
    found, _ = replay_commands.replay_file(str(edited))
    label = f"seq {began['seq']} (takeoff, run {began['call']} step {began['step']}) Aimed("
    assert [why.startswith(label) for why in found.differences] == [True, True], found.differences
    assert "action.reason" in found.differences[0]
    assert found.differences[1].endswith(f": transition {began['transition']} is {TakeoffBegan(reason)!r}, the step "
                                         f"made {TakeoffBegan(reason + '!')!r}")
