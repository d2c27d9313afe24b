"""Replay of the split-and-swap loop's decisions: a real `SplitSwap` on a real `Control`, wired
to a real Recorder as the service wires them, plans three times (a plan refused; a plan that
comes after its split, moved later from the hold; a flown plan changed while planning, planned
again), recorded into a real MCAP file; replay runs every step again alike (exit 0), each swap
the loop observed being its /control/swap record; a changed state, today's rule changed, a
removed record, records the recorder dropped and a swap record that is not what the loop saw
are each named (exit 1)."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from recorder_support import config, schema_checked
from test_replay_swaps import run
from test_replay_transitions import rewrite

from companion import replay_split
from companion.control import SWAP_LATE, Control
from companion.recorder import Recorder
from companion.route import Outcome
from companion.setpoints import Feed, YawPolicy
from companion.split_rules import SplitRules, first_state
from companion.split_swap import SplitSwap
from planner_core import Trajectory
from tests.companion.test_route import fly

TOPIC = "/navigator/split"
HERE = np.array([0.0, 0.0, -1.5])


class Target:
    feed: Feed | None = None
    lead = 0.06


async def _plans(split: SplitSwap, ctl: Control) -> list[Any]:
    """Three plans made in flight, as the navigator asks for them."""
    async def refused(_base: Trajectory, _t_split: float) -> Outcome:
        return Outcome(False, message="the planner found no plan")

    async def late(_base: Trajectory, t_split: float) -> Outcome:
        await asyncio.sleep(0.15)  # after its split, 0.05 s ahead
        return Outcome(True, route=fly([[2.0, 0.0, -1.5], [2.0, 2.0, -1.5]], HERE.tolist(), t0=t_split))

    changes = [0]

    async def changed(_base: Trajectory, t_split: float) -> Outcome:
        at = np.asarray(ctl.jet(ctl.now())[0], dtype=float)
        if not changes[0]:  # a stop came first: the flown plan is a hold here now
            changes[0] += 1
            ctl.hold_here(at)
        return Outcome(True, route=fly([[float(at[0]) + 1.0, float(at[1]), -1.5]], at.tolist(), t0=t_split))

    return [await split.at_split("refused", None, refused),
            await split.at_split("late", None, late, ahead=0.05),
            await split.at_split("changed", None, changed, ahead=1.0)]


def recorded(tmp_path: Path, queue: int = 4096, early: int = 0) -> tuple[Path, Recorder, list[Any]]:
    """`early`: as many one-step calls before the writer thread starts (they wait in the queue,
    or are dropped)."""
    rec = Recorder(config(tmp_path, queue=queue))
    ctl = Control(Target(), lambda sp: None, YawPolicy("fixed", 0.0, 0.5), 50.0)
    ctl.observe_swap = rec.swap
    flight = SimpleNamespace(flying_ours=True, state=SimpleNamespace(value="STREAMING"))
    split = SplitSwap(config(), flight, ctl, None, None)  # type: ignore[arg-type]
    split.observe = rec.split_step
    ctl.take(HERE, 0.0, "test")
    time.sleep(0.02)
    for i in range(early):  # a call that found the flight no longer ours
        from companion.split_rules import Attempt, split_step

        rules = SplitRules(0.15)
        rec.split_step(100 + i, 1, "early", rules, first_state(rules), Attempt(False, "IDLE", None),
                       *split_step(rules, first_state(rules), Attempt(False, "IDLE", None)))
    rec.open()
    done = asyncio.run(_plans(split, ctl))
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    return path, rec, done


def steps(path: Path, topic: str = TOPIC) -> list[dict[str, Any]]:
    with open(path, "rb") as fh:
        return [json.loads(m.data) for _s, _c, m in make_reader(fh).iter_messages(topics=[topic])]


def line(out: str) -> str:
    return next(ln for ln in out.splitlines() if ln.startswith("splits:"))


def test_every_step_is_recorded_and_reproduced(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, rec, done = recorded(tmp_path)
    assert [d.ok for d in done] == [False, True, True] and done[0].reason == "the planner found no plan"
    recs = steps(path)
    assert rec.dropped == {} and [r["seq"] for r in recs] == list(range(1, len(recs) + 1))
    calls = sorted({r["call"] for r in recs})
    assert calls == [1, 2, 3] and all([r["step"] for r in recs if r["call"] == c] ==
                                      list(range(1, 1 + sum(r["call"] == c for r in recs))) for c in calls)
    kinds = [(r["observation"]["type"], r["action"]["type"]) for r in recs]
    # the late plan moved later from the hold; the changed one planned again
    assert ("SwapDecided", "CheckHeld") in kinds and ("Held", "MoveLater") in kinds and ("Moved", "Done") in kinds
    assert ("Planned", "Again") in kinds and kinds[:2] == [("Attempt", "PlanAt"), ("Planned", "Refused")]
    late = next(r for r in recs if r["observation"]["type"] == "SwapDecided")
    assert late["observation"]["fields"]["refusal"] == SWAP_LATE
    assert done[1].t_split == next(r for r in recs if r["action"]["type"] == "Done")["action"]["fields"]["t_split"]
    assert schema_checked(path, TOPIC, "bezier.SplitStep") == recs
    code, out = run(path, capsys)
    assert code == 0, out
    assert f"splits: {len(recs)} of {len(recs)} reproduced (2 swapped in, 1 given up)" in out.splitlines()
    found, _ = replay_split.replay_file(str(path))
    swapped = [s for s in steps(path, "/control/swap") if s["what"] in ("late", "changed")]
    assert found.swaps_checked == len(swapped) >= 3  # every swap decided for these plans was seen by the loop


def test_a_changed_state_is_found_with_its_seq(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _rec, _d = recorded(tmp_path / "rec")
    target = next(r["seq"] for r in steps(path) if r["action"]["type"] == "CheckHeld")

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "after": {**r["after"], "t_later": r["after"]["t_later"] + 1.0}} if r["seq"] == target else r

    code, out = run(rewrite(path, tmp_path / "changed.mcap", edit, topic=TOPIC), capsys)
    assert code == 1, out
    said = line(out)
    assert said.startswith(f"splits: {len(steps(path)) - 2} of {len(steps(path))} reproduced; first difference: seq "
                           f"{target} (late, call 2 step 3) SwapDecided("), said
    assert "after.t_later" in said


def test_todays_rule_is_what_runs_again(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """A rule that changed since the flight (here: a late swap is no longer told apart, so no
    plan is moved later) makes the recorded step differ."""
    path, _rec, _d = recorded(tmp_path / "rec")
    from companion import split_rules

    monkeypatch.setattr(split_rules, "SWAP_LATE", "something else")
    code, out = run(path, capsys)
    assert code == 1, out
    target = next(r["seq"] for r in steps(path) if r["action"]["type"] == "CheckHeld")
    assert f"first difference: seq {target} (late, call 2 step 3) SwapDecided(" in line(out)
    assert f"after.reason: recorded '', replayed {SWAP_LATE!r}" in line(out)


def test_a_removed_record_is_a_gap(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _rec, _d = recorded(tmp_path / "rec")
    code, out = run(rewrite(path, tmp_path / "removed.mcap", lambda r: None if r["seq"] == 4 else r, topic=TOPIC),
                    capsys)
    assert code == 1, out
    assert line(out).startswith(f"splits: {len(steps(path)) - 1} of {len(steps(path))} reproduced; first difference: "
                                "seq 4 missing (1 record: dropped by the recorder, or removed)")


def test_records_the_recorder_dropped_are_said(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, rec, _d = recorded(tmp_path, queue=1, early=4)
    dropped = rec.dropped.get("split_step", 0)
    assert dropped >= 3  # the first waited in the queue of one (later ones may find it full too)
    kept = [r["seq"] for r in steps(path)]
    assert kept[0] == 1 and kept[1] > 2
    found, recorded_any = replay_split.replay_file(str(path))
    assert recorded_any and found.differences[-1].startswith(
        f"the recorder dropped {dropped} split step records in this run (its queue was full)")
    code, out = run(path, capsys)
    assert code == 1, out
    assert line(out).startswith("splits: ") and "first difference: seq 2 " in line(out) and "missing" in line(out)


def test_a_swap_record_unlike_the_one_the_loop_saw_is_found(tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    path, _rec, _d = recorded(tmp_path / "rec")
    moved = next(r for r in steps(path) if r["observation"]["type"] == "Moved")
    edited = rewrite(path, tmp_path / "swap.mcap",
                     lambda r: {**r, "what": "something else"} if r["seq"] == moved["swap"] else r,
                     topic="/control/swap")
    code, out = run(edited, capsys)
    assert code == 1, out
    assert f"first difference: seq {moved['seq']} (late, call 2 step 5) Moved(refusal=''): swap {moved['swap']} is " \
        "('something else'" in line(out), line(out)
