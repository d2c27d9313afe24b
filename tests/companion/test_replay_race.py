"""Replay of the pop-ups' decisions and their races: a real `Brakes` and `Supervisor` wired to a
real Recorder as the service wires them (the stop's planning and the swap stand in), five
pop-ups: one while no mission is flown, one the flown plan stays clear of, one too close to
replan (a brake), a race whose replan is swapped in, one whose replan fails (a brake naming the
blocked waypoint) and one whose replan is late, brought forward by a nearer pop-up (the stop
prepared for the deadline swapped in); recorded into a real MCAP file, replay runs every step
again alike (exit 0) and finds each brake's Braking transition; a changed state, today's rule
changed, a removed record, records the recorder dropped, a Braking transition no step asked
for and a brake whose transition is missing are each named (exit 1)."""

from __future__ import annotations

import asyncio
import json
import time
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from recorder_support import config, schema_checked
from test_replay_swaps import run
from test_replay_tracking import UP
from test_replay_transitions import rewrite

import companion.braking as braking
from companion import replay_race
from companion.braking import Brakes, Replanned, StopContext, StopGuard, StopPlan
from companion.race_rules import Forward, PopUp, Race, RaceRules, first_state, race_step
from companion.recorder import Recorder
from companion.report import Reporter
from companion.supervisor import StoppedAfterBraking, Supervisor
from companion.wire.messages import bounds_from
from planner_core import hold

TOPIC = "/brakes/race"
HERE = np.array([0.0, 0.0, -1.5])


class Rig:
    def __init__(self, rec: Recorder, pool: ThreadPoolExecutor) -> None:
        self.sup = Supervisor()
        self.sup.connect(observe=rec.transition)
        for e in UP:
            self.sup.handle(e)
        self.t0 = time.monotonic()
        base = hold(HERE, 0.0)
        self.control = SimpleNamespace(now=self.now, committed=lambda: self.now() + 0.06, active=base, flying=True,
                                       clock=lambda: (lambda: self.now() + 0.06), swap=lambda *_a: True,
                                       hold_here=lambda _p: None)
        ctx = StopContext(None, (), bounds_from(None, rec.cfg))
        self.events: list[dict[str, Any]] = []
        report = Reporter(self.sup, publish=lambda _k, body: self.events.append(body))
        self.brakes = Brakes(rec.cfg, self.sup, self.control, SimpleNamespace(loop=None, brake_pool=pool),  # type: ignore[arg-type]
                             report, lambda: ctx, lambda: HERE)
        self.brakes.observe = rec.race_step

    def now(self) -> float:
        return time.monotonic() - self.t0

    async def popup(self, names: str, hit: float | None, in_flight: bool = True) -> Any:
        """A pop-up decided as Replans.avoid decides it: a brake too close is carried out."""
        steps = self.brakes.race_steps(names)
        now = self.now()
        action = steps.step(PopUp(in_flight, now, None if hit is None else now + hit, self.control.committed()))
        if isinstance(action, braking.Brake):
            await self.brakes.brake(action.reason, time.monotonic())
        return steps, action

    async def race(self, names: str, deadline: float, replan: Replanned | None,
                   forward: tuple[float, float] | None = None) -> None:
        """A race as Replans._avoid_race runs it: the replan ends after 50 ms with `replan` (None:
        never), the deadline `deadline` s from now, a nearer pop-up (when, its deadline) maybe."""
        steps, action = await self.popup(names, 3.0)
        assert action == Race() and steps.state.hit is not None
        loop = asyncio.get_running_loop()
        guard = StopGuard(self.control.active, steps.state.hit)
        guard.steps = steps
        task: asyncio.Future[Replanned] = loop.create_future()
        if replan is not None:
            loop.call_later(0.05, task.set_result, replan)
        now = self.now()
        guard.bring_forward(now + deadline, steps.state.hit)
        if forward is not None:
            loop.call_later(forward[0], guard.bring_forward, now + forward[1], steps.state.hit - 0.5, "['near']")
        await self.brakes.race(guard, task, ["local replan: no"], time.monotonic(), steps.rules.what)  # type: ignore[arg-type]

    def stopped(self) -> None:
        self.sup.handle(StoppedAfterBraking())


def _plan_stop(_base: Any, starts: list[float], *_a: Any, **_kw: Any) -> StopPlan:
    return StopPlan(hold(HERE, starts[0]), starts[0], "a verified stop", True)


def recorded(tmp_path: Path, monkeypatch: pytest.MonkeyPatch, queue: int = 4096,
             early: int = 0) -> tuple[Path, Recorder, Rig]:
    """`early`: as many one-step pop-ups before the writer thread starts (they wait in the
    queue, or are dropped)."""
    monkeypatch.setattr(braking, "plan_stop", _plan_stop)
    rec = Recorder(config(tmp_path, queue=queue))
    with ThreadPoolExecutor(1) as pool:
        rig = Rig(rec, pool)
        for i in range(early):
            rules = RaceRules(f"['e{i}']", f"obstacles ['e{i}']", 0.15, 0.04)
            rec.race_step(100 + i, 1, rules, first_state(), PopUp(False),
                          *race_step(rules, first_state(), PopUp(False)))
        rec.open()

        async def popups() -> None:
            rig.brakes.runtime.loop = asyncio.get_running_loop()
            await rig.popup("['idle']", None, in_flight=False)
            await rig.popup("['aside']", None)
            await rig.race("['won']", 2.0, Replanned(True))
            await rig.race("['wall']", 2.0, Replanned(False, "local replan: no", 2, "inside 'wall'"))
            rig.stopped()
            await rig.race("['late']", 1.0, None, forward=(0.1, 0.6))
            rig.stopped()
            await rig.popup("['close']", 0.1)

        asyncio.run(popups())
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    return path, rec, rig


def steps(path: Path, topic: str = TOPIC) -> list[dict[str, Any]]:
    with open(path, "rb") as fh:
        return [json.loads(m.data) for _s, _c, m in make_reader(fh).iter_messages(topics=[topic])]


def line(out: str) -> str:
    return next(ln for ln in out.splitlines() if ln.startswith("races:"))


def test_every_step_is_recorded_and_reproduced(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    path, rec, rig = recorded(tmp_path, monkeypatch)
    recs = steps(path)
    assert rec.dropped == {} and [r["seq"] for r in recs] == list(range(1, len(recs) + 1))
    races = sorted({r["call"] for r in recs})
    assert races == list(range(1, 7)) and all([r["step"] for r in recs if r["call"] == n] ==
                                              list(range(1, 1 + sum(r["call"] == n for r in recs))) for n in races)
    by_race = {n: [(r["observation"]["type"], r["action"]["type"]) for r in recs if r["call"] == n] for n in races}
    assert by_race[1] == [("PopUp", "Announce")] and by_race[2] == [("PopUp", "Clear")]
    assert by_race[3][:2] == [("PopUp", "Race"), ("Forward", "Forwarded")] and by_race[3][-1] == ("ReplanOver", "Won")
    assert by_race[4][-1] == ("ReplanOver", "Brake")
    assert ("Tick", "Prepare") in by_race[5] and ("Forward", "Forwarded") in by_race[5][2:]
    assert by_race[5][-3:] == [("Tick", "Deadline"), ("ReplanCancelled", "SwapPrepared"), ("PreparedSwap", "Braked")]
    assert by_race[6] == [("PopUp", "Brake")]
    braked = [e for e in rig.events if e["type"] == "braking"]
    assert len(braked) == 3 and "mission waypoint 2 is blocked (inside 'wall')" in braked[0]["reason"]
    assert "brought forward by obstacles ['near']" in braked[1]["reason"] and "too close" in braked[2]["reason"]
    assert schema_checked(path, TOPIC, "bezier.RaceStep") == recs
    code, out = run(path, capsys)
    assert code == 0, out
    assert f"races: {len(recs)} of {len(recs)} reproduced (6 pop-ups, 3 raced, 3 brakes, 3 followed by its " \
        "Braking transition)" in out.splitlines(), out


def test_a_changed_state_is_found_with_its_seq(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    path, _rec, _rig = recorded(tmp_path / "rec", monkeypatch)
    target = next(r["seq"] for r in steps(path) if r["action"]["type"] == "SwapPrepared")

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "after": {**r["after"], "deadline": r["after"]["deadline"] + 1.0}} if r["seq"] == target else r

    code, out = run(rewrite(path, tmp_path / "changed.mcap", edit, topic=TOPIC), capsys)
    assert code == 1, out
    said = line(out)
    # the step itself, and the next one whose state before is not what it ended in
    assert said.startswith(f"races: {len(steps(path)) - 2} of {len(steps(path))} reproduced; first difference: seq "
                           f"{target} (obstacles ['late'], race 5 step "), said
    assert "after.deadline" in said


def test_todays_rule_is_what_runs_again(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                        monkeypatch: pytest.MonkeyPatch) -> None:
    """A rule that changed since the flight (here: a stop not yet planned is no longer told
    apart, so the first deadline brought forward drops a stop there is not) makes the recorded
    step differ."""
    path, _rec, _rig = recorded(tmp_path / "rec", monkeypatch)
    from companion import race_rules

    monkeypatch.setattr(race_rules, "NONE", "something else")
    code, out = run(path, capsys)
    assert code == 1, out
    target = next(r["seq"] for r in steps(path) if r["observation"]["type"] == "Forward")
    assert f"first difference: seq {target} (obstacles ['won'], race 3 step 2) Forward(" in line(out), line(out)
    assert "action.cancel: recorded False, replayed True" in line(out), line(out)


def test_a_removed_record_is_a_gap(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                   monkeypatch: pytest.MonkeyPatch) -> None:
    path, _rec, _rig = recorded(tmp_path / "rec", monkeypatch)
    code, out = run(rewrite(path, tmp_path / "removed.mcap", lambda r: None if r["seq"] == 4 else r, topic=TOPIC),
                    capsys)
    assert code == 1, out
    assert line(out).startswith(f"races: {len(steps(path)) - 1} of {len(steps(path))} reproduced; first difference: "
                                "seq 4 missing (1 record: dropped by the recorder, or removed)")


def test_records_the_recorder_dropped_are_said(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    path, rec, _rig = recorded(tmp_path, monkeypatch, queue=1, early=4)
    dropped = rec.dropped.get("race_step", 0)
    assert dropped >= 3  # the first waited in the queue of one (later ones may find it full too)
    found, recorded_any = replay_race.replay_file(str(path), [])
    assert recorded_any and found.differences[-1].startswith(
        f"the recorder dropped {dropped} race step records in this run (its queue was full)")


def test_a_brake_without_its_transition_and_a_transition_without_its_brake(tmp_path: Path,
                                                                           capsys: pytest.CaptureFixture[str],
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """A Braking transition of an obstacle's reason that no step asked for is a difference; a
    brake whose transition is not there is counted as not followed."""
    path, _rec, _rig = recorded(tmp_path / "rec", monkeypatch)
    braked = next(r for r in steps(path) if r["action"]["type"] == "Braked")
    recs = steps(path)

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        if r["seq"] == braked["seq"]:
            return {**r, "action": {**r["action"], "fields": {**r["action"]["fields"], "reason": "obstacles: other"}}}
        return r

    code, out = run(rewrite(path, tmp_path / "untied.mcap", edit, topic=TOPIC), capsys)
    assert code == 1, out
    said = line(out)
    assert f"first difference: seq {braked['seq']} " in said and "action.reason" in said, said
    found, _ = replay_race.replay_file(str(tmp_path / "untied.mcap"),
                                       steps(tmp_path / "untied.mcap", "/supervisor/transition"))
    assert found.brakes == 3 and found.tied == 2
    assert any(d.startswith("transition ") and "was asked for by no recorded race step" in d
               for d in found.differences), found.differences
    assert len(recs) == len(steps(tmp_path / "untied.mcap"))


def test_records_that_begin_mid_race_need_not_claim_a_brake_asked_for_before_them(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A file part (or a time range) that begins with a braking race's deadline step, after its
    brake but before its Braking transition, does not name that transition; one that begins
    with a pop-up does."""
    path, _rec, _rig = recorded(tmp_path / "rec", monkeypatch)
    transitions = steps(path, "/supervisor/transition")
    wall = next(r for r in steps(path) if r["action"]["type"] == "Brake" and r["call"] == 4)
    rules, _b, _o, after, _a = replay_race.step_values(wall)
    seen = Forward(after.deadline - 0.5, after.hit, "['near']", "none", None)
    later, action = race_step(rules, after, seen)

    def record(step: int, before: Any, observation: Any, new: Any, act: Any) -> dict[str, Any]:
        from companion import channels

        return json.loads(channels.dumps({"seq": 1, "t": 0.0, "transition": wall["transition"],
                                          **channels.split_fields(4, step, rules.what, rules, before, observation, new,
                                                                            act)}))

    mid = replay_race.replay_steps([record(wall["step"] + 1, after, seen, later, action)], 0, transitions)
    assert mid.differences == [] and mid.total == mid.reproduced == 1
    popup = PopUp(True, 1.0, 4.0, 1.1)
    fresh = replay_race.replay_steps([record(1, first_state(), popup, *race_step(rules, first_state(), popup))], 0,
                                     transitions)
    assert any("was asked for by no recorded race step" in d for d in fresh.differences), fresh.differences
