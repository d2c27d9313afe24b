"""The hand-over's hold confirmation as one rule (companion.hold_rules.hold_step) and its replay.

The rule decides as `HandOver._confirm_hold` did before it was one pure function (an oracle copy
of that loop, verbatim but for the clock, on generated vehicles: holding, drifting, descending,
leaving the mode, disarming); a real HandOver watching a vehicle that holds and one that sinks,
shown to a real Recorder, writes every sample it judged into a real MCAP file, which replay runs
again alike (exit 0); a changed verdict, a replaced state, a step after the verdict, a removed
record and today's rule changed are each named by their seq (exit 1); a record naming another
class is refused (exit 2)."""

from __future__ import annotations

import asyncio
import itertools
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from recorder_support import config, schema_checked
from test_replay_transitions import rewrite

from companion import hold_rules, replay_cli
from companion.handover import HandOver, HoldProfile
from companion.hold_rules import (
    POLL,
    Began,
    Fails,
    HoldRules,
    Holds,
    HoldState,
    Seen,
    Watch,
    hold_step,
)
from companion.recorder import Recorder

TOPIC = "/handover/hold"


def _old(pr: HoldProfile, start: float, z0: float, mode_now: str, settle_given: float | None,
         samples: list[tuple[float, bool, str, float, np.ndarray]]) -> tuple[Any, ...]:
    """The confirmation loop as it was before the rule, verbatim but for the clock (each sample
    carries the loop's time); the oracle."""
    worst_dz, worst_v = 0.0, 0.0
    settle_by = settle_given if settle_given is not None else start + pr.settle
    done_by, latest = start + pr.confirm, max(start + pr.confirm, min(settle_by, start + pr.settle) + 1.0)
    settled = False
    problem = None
    now, it = start, iter(samples)
    while now < latest and not (settled and now >= done_by):
        now, armed, mode, z, velocity = next(it)
        dz = float(z) - z0
        speed = float(np.linalg.norm(velocity))
        worst_dz = dz if abs(dz) > abs(worst_dz) else worst_dz
        worst_v = max(worst_v, speed)
        settled = settled or speed <= pr.speed_tolerance or now >= settle_by
        if not armed:
            problem = "the vehicle disarmed"
        elif mode != mode_now:
            problem = f"the autopilot left {mode_now} for {mode}"
        elif abs(dz) > pr.altitude_tolerance:
            problem = f"the vehicle {'descends' if dz > 0 else 'climbs'}: {abs(dz):.2f} m from where the hold began"
        elif settled and speed > pr.speed_tolerance:
            vz = float(velocity[2])
            how = f" ({'descending' if vz > 0 else 'climbing'} at {abs(vz):.2f} m/s)" if abs(vz) >= 0.5 * speed else ""
            problem = f"the vehicle moves at {speed:.2f} m/s{how}"
        if problem is not None:
            break
    return problem, worst_dz, worst_v, round(now - start, 2)


def _vehicle(seed: int) -> tuple[HoldProfile, float, float, float | None, list[tuple[float, bool, str, float, Any]]]:
    """A generated hold: a profile, where it began, and the vehicle sampled every POLL s (its
    speed decaying from a few m/s, drifting, now and then sinking, leaving the mode, disarming)."""
    rng = np.random.default_rng(seed)
    pr = HoldProfile(settle=float(rng.uniform(0.5, 3.0)), speed_tolerance=float(rng.uniform(0.2, 1.0)),
                     altitude_tolerance=float(rng.uniform(0.2, 1.0)), confirm=float(rng.uniform(0.5, 3.0)),
                     exit_timeout=9.0)
    start, z0 = float(rng.uniform(0, 1000)), float(rng.uniform(-20, -1))
    settle_given = None if rng.random() < 0.5 else start + float(rng.uniform(-0.5, 2.5))
    v0, decay = rng.normal(0, 1.5, 3), float(rng.uniform(0.2, 2.0))
    sink = float(rng.choice([0.0, 0.0, rng.uniform(0.05, 0.8)]))
    leave_at, disarm_at = (int(rng.integers(5, 120)) if rng.random() < 0.2 else None for _ in range(2))
    out, t, z = [], start, z0
    for k in range(200):
        t += POLL
        v = v0 * np.exp(-decay * (t - start)) + rng.normal(0, 0.08, 3) + np.array([0.0, 0.0, sink])
        z += float(v[2]) * POLL
        out.append((t, disarm_at is None or k < disarm_at, "LOITER" if leave_at is None or k < leave_at else "LAND",
                    z, v))
    return pr, start, z0, settle_given, out


@settings(max_examples=300, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_the_rule_decides_as_the_loop_did(seed: int) -> None:
    pr, start, z0, settle_given, samples = _vehicle(seed)
    rules = HoldRules(pr.altitude_tolerance, pr.speed_tolerance, pr.settle, pr.confirm)
    state, action = hold_step(rules, HoldState(), Began(start, z0, "LOITER", settle_given))
    for t, armed, mode, z, v in samples:
        if not isinstance(action, Watch):
            break
        state, action = hold_step(rules, state, Seen(t, armed, mode, z, (float(v[0]), float(v[1]), float(v[2]))))
    assert isinstance(action, Holds | Fails)
    problem = action.problem if isinstance(action, Fails) else None
    assert (problem, state.worst_dz, state.worst_v, action.watched) == _old(pr, start, z0, "LOITER", settle_given,
                                                                            samples)


PROFILE = HoldProfile(settle=0.3, speed_tolerance=0.5, altitude_tolerance=0.5, confirm=0.5, exit_timeout=9.0)


def _watched(tmp_path: Path, queue: int = 4096) -> tuple[Path, list[bool], list[tuple[str, dict[str, Any]]]]:
    """A real HandOver (its link's state a stand-in the test moves) shown to a real Recorder:
    a vehicle that settles and holds, then one that sinks at 1.5 m/s."""
    rec = Recorder(config(tmp_path, queue=queue))
    events: list[tuple[str, dict[str, Any]]] = []
    state = SimpleNamespace(position=np.array([1.0, 2.0, -5.0]), velocity=np.array([0.8, 0.0, 0.0]), armed=True,
                            mode="LOITER")
    ho = HandOver.__new__(HandOver)
    ho.link = SimpleNamespace(state=state)  # type: ignore[assignment]
    ho.report = SimpleNamespace(event=lambda kind, msg, **f: events.append((msg, f)))  # type: ignore[assignment]
    ho.hold_profile = lambda: PROFILE  # type: ignore[method-assign]
    ho._settle_by, ho._holds, ho.observe = None, itertools.count(1), rec.hold_step
    rec.open()
    verdicts = []

    async def main() -> None:
        async def slow_down() -> None:
            for _ in range(4):
                await asyncio.sleep(0.05)
                state.velocity = state.velocity * 0.3

        mover = asyncio.create_task(slow_down())
        verdicts.append(await ho._confirm_hold("exit", "LOITER", "AUTO.LOITER holds without a pilot"))
        await mover
        state.velocity = np.array([0.0, 0.0, 1.5])

        async def sink() -> None:
            for _ in range(20):
                await asyncio.sleep(0.05)
                state.position = state.position + state.velocity * 0.05

        sinking = asyncio.create_task(sink())
        verdicts.append(await ho._confirm_hold("exit", "LOITER", "AUTO.LOITER holds without a pilot"))
        sinking.cancel()

    asyncio.run(main())
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    return path, verdicts, events


@pytest.fixture(scope="module")
def watched(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[bool], list[tuple[str, dict[str, Any]]]]:
    return _watched(tmp_path_factory.mktemp("hold"))


def run(path: Path, capsys: pytest.CaptureFixture[str], *args: str) -> tuple[int, str]:
    code = replay_cli.main([str(path), *args])
    return code, next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("holds:"))


def test_each_sample_judged_is_recorded_and_replayed_alike(watched: Any, capsys: pytest.CaptureFixture[str]) -> None:
    path, verdicts, events = watched
    assert verdicts == [True, False]
    assert events[0][1]["held"] and "holds the vehicle in LOITER" in events[0][0]
    assert not events[1][1]["held"] and "does not hold: the vehicle" in events[1][0] and "descend" in events[1][0]
    recs = schema_checked(path, TOPIC, "bezier.HoldStep")
    assert [r["seq"] for r in recs] == list(range(1, len(recs) + 1))
    for call in (1, 2):
        mine = [r for r in recs if r["call"] == call]
        assert [r["step"] for r in mine] == list(range(1, len(mine) + 1))
        assert mine[0]["observation"]["type"] == "Began" and len(mine) >= 4
        assert [r["action"]["type"] for r in mine[:-1]] == ["Watch"] * (len(mine) - 1)
        assert mine[-1]["action"]["type"] == ("Holds" if call == 1 else "Fails")
    assert run(path, capsys) == (0, f"holds: {len(recs)} of {len(recs)} reproduced (1 held, 1 not held)")


def _seqs(path: Path) -> dict[str, int]:
    recs = schema_checked(path, TOPIC, "bezier.HoldStep")
    return {"holds": next(r["seq"] for r in recs if r["action"]["type"] == "Holds"),
            "second": next(r["seq"] for r in recs if r["call"] == 2 and r["step"] == 2)}


def test_a_changed_verdict_is_named(tmp_path: Path, watched: Any, capsys: pytest.CaptureFixture[str]) -> None:
    at = _seqs(watched[0])["holds"]

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        if r["seq"] != at:
            return r
        return {**r, "action": {"type": "Fails", "fields": {"problem": "made up", "watched": 0.5}}}

    code, line = run(rewrite(watched[0], tmp_path / "verdict.mcap", edit, topic=TOPIC), capsys)
    assert code == 1 and f"first difference: seq {at} (hold 1 step " in line and "action" in line, line


def test_a_state_replaced_and_a_step_after_the_verdict_are_named(tmp_path: Path, watched: Any,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    at = _seqs(watched[0])["second"]

    def replaced(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "before": {**r["before"], "z0": r["before"]["z0"] + 1.0}} if r["seq"] == at else r

    code, line = run(rewrite(watched[0], tmp_path / "chain.mcap", replaced, topic=TOPIC), capsys)
    assert code == 1 and f"seq {at} (hold 2 step 2)" in line and f"does not start where seq {at - 1} ended" in line

    last = _seqs(watched[0])["holds"]

    def verdict_early(r: dict[str, Any]) -> dict[str, Any]:  # step 2 of hold 1 made the verdict
        if r["call"] == 1 and r["step"] == 2:
            return {**r, "action": {"type": "Holds", "fields": {"watched": 0.05}}}
        return r

    code = replay_cli.main([str(rewrite(watched[0], tmp_path / "after.mcap", verdict_early, topic=TOPIC)),
                            "--keep-going"])
    out = capsys.readouterr().out
    assert code == 1 and "(hold 1 step 3)" in out and "follows the verdict of step 2 (Holds(watched=0.05))" in out, out
    assert last > 3


def test_a_removed_record_is_a_gap(tmp_path: Path, watched: Any, capsys: pytest.CaptureFixture[str]) -> None:
    code, line = run(rewrite(watched[0], tmp_path / "gap.mcap", lambda r: None if r["seq"] == 3 else r, topic=TOPIC),
                     capsys)
    assert code == 1 and "seq 3 missing (1 record" in line, line


def test_todays_rule_changed_is_a_difference(watched: Any, capsys: pytest.CaptureFixture[str],
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(hold_rules, "POLL", 0.1)
    code, line = run(watched[0], capsys)
    assert code == 1 and "action" in line, line


def test_a_record_naming_another_class_is_refused(tmp_path: Path, watched: Any,
                                                  capsys: pytest.CaptureFixture[str]) -> None:
    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "observation": {"type": "Popen", "fields": {"args": ["true"]}}} if r["seq"] == 1 else r

    code = replay_cli.main([str(rewrite(watched[0], tmp_path / "foreign.mcap", edit, topic=TOPIC))])
    err = capsys.readouterr().err
    assert code == 2 and "'Popen' is not a hold observation or action" in err, err
