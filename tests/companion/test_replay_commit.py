"""Replay of the fleet's commit protocol (/fleet/commit): a real Deconfliction's calls of the
rule, shown to a real Recorder, written into a real MCAP file, run again alike (exit 0); a
changed action, a replaced state, a removed record, a first record not from an idle state and
today's rule changed are each named by their seq (exit 1); a record naming another class is
refused (exit 2). (A recorded flight: tests/mock/test_fleet_clock.py.)"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from recorder_support import config, schema_checked
from test_replay_transitions import rewrite

from companion import replay_cli
from companion.commit import Cancel, Heard, Other, Rank, Ready, Tick
from companion.deconfliction import Deconfliction
from companion.fleet import FleetFrame
from companion.recorder import Recorder

TOPIC = "/fleet/commit"
ME = "drone1"
HIGH, LOW = Rank(1, "drone0"), Rank(0, "drone9")  # one outranks us, one we outrank
# a service's calls: a candidate proposed and committed at its deadline (a lower-ranked proposal
# heard meanwhile is ignored); one that loses at once to a committed conflict; one proposed, then
# lost to a higher-ranked proposal heard; idle, a higher-ranked commit conflicting with ours
# (replan); a cancel
EVENTS = [Ready(1, 10.0, ()), Heard(10.05, Other(LOW, False, True)), Tick(10.2),
          Ready(2, 12.0, (Other(LOW, True, True),)),
          Ready(3, 13.0, (Other(LOW, False, False),)), Heard(13.1, Other(HIGH, False, True)),
          Heard(14.0, Other(HIGH, True, False, True)), Cancel()]


def _recorded(tmp_path: Path) -> tuple[Path, list[Any]]:
    cfg = config(tmp_path)
    rec = Recorder(cfg)
    dec = Deconfliction(cfg, FleetFrame(cfg.fleet), lambda: None, lambda _b: None, lambda *_a, **_k: None)
    calls: list[Any] = []

    def seen(*call: Any) -> None:
        calls.append(call)
        rec.commit_step(*call)

    dec.observe = seen
    rec.open()
    for e in EVENTS:
        dec._step(e)
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    return path, calls


@pytest.fixture(scope="module")
def flown(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _recorded(tmp_path_factory.mktemp("commit"))[0]


def run(path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = replay_cli.main([str(path)])
    out = capsys.readouterr().out
    return code, next((ln for ln in out.splitlines() if ln.startswith("fleet commits:")), out)


def test_every_call_is_recorded_in_order_and_runs_again_alike(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    path, calls = _recorded(tmp_path)
    recs = schema_checked(path, TOPIC, "bezier.CommitStep")
    assert [r["seq"] for r in recs] == list(range(1, len(EVENTS) + 1))
    acts = [[a["type"] for a in r["actions"]] for r in recs]
    assert acts == [[type(a).__name__ for a in c[3]] for c in calls]
    # what the protocol decided, as the docstring of companion.commit says it must
    assert acts == [["Propose"], [], ["Commit"], ["Lose"], ["Propose"], ["Lose"], ["Replan"], []]
    assert json.loads(json.dumps(recs)) == recs  # JSON only
    assert run(path, capsys) == (0, f"fleet commits: {len(EVENTS)} of {len(EVENTS)} reproduced (1 committed, 2 lost)")


def test_a_changed_action_is_named(tmp_path: Path, flown: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def edit(r: dict[str, Any]) -> dict[str, Any]:
        if r["seq"] != 6:
            return r
        lose = r["actions"][0]
        return {**r, "actions": [{**lose, "fields": {**lose["fields"], "winner": "drone9"}}]}

    code, line = run(rewrite(flown, tmp_path / "action.mcap", edit, topic=TOPIC), capsys)
    assert code == 1 and "first difference: seq 6 Heard: actions" in line and "drone9" in line, line


def test_a_state_replaced_outside_the_rule_is_named(tmp_path: Path, flown: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    def edit(r: dict[str, Any]) -> dict[str, Any]:
        if r["seq"] != 3:
            return r
        moved = {**r["before"], "deadline": r["before"]["deadline"] + 1.0}
        return {**r, "before": moved}

    code, line = run(rewrite(flown, tmp_path / "chain.mcap", edit, topic=TOPIC), capsys)
    assert code == 1 and "seq 3 Tick: does not start where seq 2 ended" in line, line


def test_a_first_record_not_idle_is_named(tmp_path: Path, flown: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "before": {**r["before"], "phase": "proposed"}} if r["seq"] == 1 else r

    code, line = run(rewrite(flown, tmp_path / "first.mcap", edit, topic=TOPIC), capsys)
    assert code == 1 and "seq 1 Ready: before (idle, as a service starts)" in line, line


def test_a_removed_record_is_a_gap(tmp_path: Path, flown: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, line = run(rewrite(flown, tmp_path / "gap.mcap", lambda r: None if r["seq"] == 4 else r, topic=TOPIC),
                     capsys)
    assert code == 1 and "seq 4 missing (1 record" in line, line


def test_todays_rule_changed_is_a_difference(flown: Path, capsys: pytest.CaptureFixture[str],
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """Were a lower-ranked proposal to win now, the flight's second call would be decided otherwise."""
    monkeypatch.setattr(Rank, "outranks", lambda self, other: True)
    code, line = run(flown, capsys)
    assert code == 1 and "first difference: seq 2 Heard" in line, line


def test_a_record_cannot_name_another_class(tmp_path: Path, flown: Path) -> None:
    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "event": {"type": "Braking", "fields": {"reason": "x"}}} if r["seq"] == 2 else r

    assert replay_cli.main([str(rewrite(flown, tmp_path / "other.mcap", edit, topic=TOPIC))]) == 2


def test_a_file_without_commits_says_nothing_of_them(tmp_path: Path, flown: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """A vehicle outside a fleet: no line about commits (and nothing else recorded: exit 2)."""
    path = rewrite(flown, tmp_path / "none.mcap", lambda r: None, topic=TOPIC)
    assert replay_cli.main([str(path)]) == 2
    assert "fleet commits" not in capsys.readouterr().out


def _clock_recorded(tmp_path: Path) -> Path:
    """Three vehicles' puts every 0.2 s, whose clocks fall 0.5 s behind ours after 2 s: the
    samples and the verdicts a real ClockCheck gave, recorded as the service records them."""
    from companion.clocks import ClockCheck

    cfg = config(tmp_path)
    rec = Recorder(cfg)
    check = ClockCheck(cfg.fleet.clock_tolerance, cfg.fleet.max_delay)
    rec.open()
    for k in range(20):
        arrived = 1000.0 + 0.2 * k
        for v in ("g1", "g2", "g3"):
            sent = arrived - 0.01 + (0.5 if k >= 10 else 0.0)
            check.heard(v, sent, arrived)
            rec.clock_sample(v, sent, arrived, check.ours_off(arrived))
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    return path


def clock_line(path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = replay_cli.main([str(path)])
    out = capsys.readouterr().out
    return code, next((ln for ln in out.splitlines() if ln.startswith("fleet clock:")), out)


def test_the_clock_checks_verdicts_are_judged_alike(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = _clock_recorded(tmp_path)
    recs = schema_checked(path, "/fleet/clock", "bezier.ClockSample")
    assert [r["seq"] for r in recs] == list(range(1, 61))
    assert recs[0]["off"] is None and recs[-1]["off"] is not None and "disagrees with 3 of the 3" in recs[-1]["off"]
    assert clock_line(path, capsys) == (0, "fleet clock: 60 of 60 judged alike (our clock found off 1 time)")


def test_a_changed_verdict_a_gap_and_todays_rule_changed_are_named(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    path = _clock_recorded(tmp_path)
    trusted = rewrite(path, tmp_path / "verdict.mcap", lambda r: {**r, "off": None} if r["seq"] == 60 else r,
                      topic="/fleet/clock")
    code, line = clock_line(trusted, capsys)
    assert code == 1 and line.startswith("fleet clock: 59 of 60 judged alike; first difference: seq 60 (g3,"), line
    gap = rewrite(path, tmp_path / "gap.mcap", lambda r: None if r["seq"] == 7 else r, topic="/fleet/clock")
    code, line = clock_line(gap, capsys)
    assert code == 1 and "seq 7 missing (1 record" in line, line
    import companion.clocks as clocks

    monkeypatch.setattr(clocks, "MIN_SAMPLES", 50)  # the check would not yet judge our clock
    code, line = clock_line(path, capsys)
    assert code == 1 and "verdict on our clock" in line, line
