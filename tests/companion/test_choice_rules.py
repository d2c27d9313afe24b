"""The navigator's plan choice as one rule (companion.choice_rules.choice_step) and its replay.

The rule chooses as the shells chose before it was one pure function: oracle copies of the old
code (a mission start's `plan_at`, a replan's `_replan_outcome`, `Brakes.brake`), verbatim but
for the planner, on generated answers; the real `Brakes.brake` (the planner and the flown plan
stand-ins that answer as told) stops, swaps the prepared stop or holds as the old code did, for
every combination. Shown to a real Recorder, the runs of a start, a replan and a stop are
written to a real MCAP file with the planner calls they chose, which replay runs again alike
(exit 0); a changed action, a replaced state, a planner call missing, a removed record and
today's rule changed are each named by their seq (exit 1); a record naming another class is
refused (exit 2)."""

from __future__ import annotations

import asyncio
import itertools
import time
from collections.abc import Iterator
from concurrent.futures import ThreadPoolExecutor
from functools import partial
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from recorder_support import config, schema_checked
from test_replay_transitions import rewrite

import companion.braking as braking
from companion import choice_rules as cr
from companion import replay_choice
from companion.braking import Brakes, StopContext, StopPlan
from companion.config import Config
from companion.flight import FlightState, State
from companion.mission import local_replan, replan_remainder, start_mission, start_separated
from companion.recorder import Recorder
from companion.route import Outcome
from companion.rule_run import Runs
from companion.supervisor import Supervisor
from companion.wire.messages import bounds_from
from planner_core import hold

TOPIC = "/navigator/choice"
INFEASIBLE, BLOCKED, OK = "INFEASIBLE", "BLOCKED", "OK"
answers = st.lists(st.tuples(st.booleans(), st.sampled_from([INFEASIBLE, BLOCKED])), min_size=8, max_size=8)


def _named(fn: Any) -> str:
    from companion.record_format import function_name

    return function_name(fn)


# -- the oracles: the old code, verbatim but for the planner ----------------------------------------


def _old_start(anytime: bool, timing: str, durations: bool, fleet: bool, cap: int, tries: int,
               planner: Iterator[tuple[bool, str]]) -> tuple[list[str], list[bool], bool]:
    quick = [anytime and not durations and timing == "fastest" and not fleet]
    calls: list[str] = []
    oks: list[bool] = []
    for _ in range(tries):
        search: Any = partial(start_mission, candidates=cap) if cap else start_mission
        fn: Any = (partial(start_separated, neighbours=None, candidates=cap)
                   if fleet else partial(start_mission, quick=True) if quick[0] else search)
        calls.append(_named(fn))
        ok, status = next(planner)
        if quick[0] and not ok and status == INFEASIBLE:
            quick[0] = False
            calls.append(_named(search))
            ok, status = next(planner)
        quick[0] = quick[0] and ok
        oks.append(ok)
    return calls, oks, quick[0]


def _new_start(anytime: bool, timing: str, durations: bool, fleet: bool, cap: int, tries: int,
               planner: Iterator[tuple[bool, str]]) -> tuple[list[str], list[bool], bool]:
    """As MissionStart.fly's plan_at asks the rule (the shell's call from the action)."""
    run = Runs(cr.choice_step, "test").run(cr.StartRules(anytime, timing, durations, fleet), cr.ChoiceState())
    calls: list[str] = []
    oks: list[bool] = []
    for _ in range(tries):
        search: Any = partial(start_mission, candidates=cap) if cap else start_mission
        action = run.step(cr.Ask())
        while True:
            assert isinstance(action, cr.Plan)
            fn: Any = (partial(start_separated, neighbours=None, candidates=cap) if action.call == cr.SEPARATED
                       else partial(start_mission, quick=True) if action.quick else search)
            calls.append(_named(fn))
            ok, status = next(planner)
            action = run.step(cr.Answer(ok, OK if ok else status, "m"))
            if isinstance(action, cr.Take):
                break
        oks.append(action.ok)
    return calls, oks, bool(run.state.quick)


@settings(max_examples=300, deadline=None)
@given(st.booleans(), st.sampled_from(["fastest", "given"]), st.booleans(), st.booleans(), st.integers(0, 40),
       st.integers(1, 3), answers)
def test_a_start_chooses_as_the_old_code_did(anytime: bool, timing: str, durations: bool, fleet: bool, cap: int,
                                             tries: int, given_answers: list[tuple[bool, str]]) -> None:
    args = (anytime, timing, durations, fleet, cap, tries)
    assert _new_start(*args, iter(given_answers)) == _old_start(*args, iter(given_answers))


@settings(max_examples=200, deadline=None)
@given(st.booleans(), st.booleans(), answers)
def test_a_replan_chooses_as_the_old_code_did(local: bool, allocate: bool, given_answers: list[tuple[bool, str]]) -> None:
    def old(planner: Iterator[tuple[bool, str]]) -> tuple[list[str], bool]:
        calls = []
        if local:
            calls.append(_named(local_replan))
            ok, _ = next(planner)
            if ok:
                return calls, True
        calls.append(_named(partial(replan_remainder, allocate=allocate, neighbours=None)))
        return calls, next(planner)[0]

    def new(planner: Iterator[tuple[bool, str]]) -> tuple[list[str], bool]:
        run = Runs(cr.choice_step, "test").run(cr.ReplanRules(local, allocate), cr.ChoiceState())
        calls = []
        action = run.step(cr.Ask())
        while isinstance(action, cr.Plan):
            calls.append(_named(local_replan) if action.call == cr.LOCAL
                          else _named(partial(replan_remainder, allocate=action.allocate, neighbours=None)))
            ok, status = next(planner)
            action = run.step(cr.Answer(ok, OK if ok else status, "m"))
        assert isinstance(action, cr.Take)
        return calls, action.ok

    assert new(iter(given_answers)) == old(iter(given_answers))


@settings(max_examples=200, deadline=None)
@given(st.booleans(), st.booleans(), st.booleans(), st.floats(0.0, 20.0), st.floats(0.0, 20.0))
def test_an_improvement_chooses_as_the_old_code_did(before: bool, after: bool, ok: bool, t_end: float,
                                                    quick_end: float) -> None:
    """`before`, `after`: the flown plan changed before the search, during it."""
    def old() -> tuple[bool, str]:
        if before:
            return False, "the flown plan changed first"
        if after:
            return False, "the flown plan changed first"
        if ok and t_end > quick_end - 0.05:
            return False, "no earlier"
        return ok, ""

    run = Runs(cr.choice_step, "test").run(cr.ImproveRules(quick_end, 0.05), cr.ChoiceState())
    action = run.step(cr.Ask(not before))
    if isinstance(action, cr.Plan):
        assert action == cr.Plan(cr.REMAINDER, allocate=True)
        action = run.step(cr.Answer(ok, OK if ok else INFEASIBLE, "m", not after, t_end))
    assert isinstance(action, cr.Take)
    new = (action.ok, "no earlier" if action.detail == cr.NO_EARLIER else action.detail)
    assert new == old()


STATES = ["IDLE", "PILOT", "FAILSAFE", "READY", "STREAMING", "HOLDING", "BRAKING"]


@settings(max_examples=300, deadline=None)
@given(st.booleans(), st.sampled_from(STATES), st.booleans(), st.booleans(), st.sampled_from(["px4", "ardupilot", ""]),
       st.lists(st.tuples(st.sampled_from(STATES), st.booleans()), min_size=3, max_size=3), st.booleans(), st.booleans())
def test_the_start_command_chooses_as_the_old_code_did(armed: bool, state: str, airborne: bool, in_air: bool,
                                                       autopilot: str, after: list[tuple[str, bool]], pending: bool,
                                                       interrupted: bool) -> None:
    """`after`: the flight state and airborne after each take-off or taking control, in turn."""

    def old() -> list[str]:  # Commands._start before the rule, its calls written down
        did: list[str] = []
        world = {"state": state, "airborne": airborne}
        outcomes = iter(after)

        def act(what: str) -> None:
            did.append(what)
            world["state"], world["airborne"] = next(outcomes)

        if not armed:
            act("takeoff")
        elif world["state"] in ("PILOT", "FAILSAFE", "IDLE"):
            if not world["airborne"] and not in_air and autopilot != "px4":
                return ["refused: vehicle is on the ground: send 'takeoff' first"]
            act("control")
        if world["state"] == "READY" and not world["airborne"]:
            act("takeoff")
        if pending:
            did.append("fly")
        elif interrupted:
            did.append("resume")
        return did

    def new() -> list[str]:  # as Commands._start asks the rule
        did: list[str] = []
        world = {"state": state, "airborne": airborne}
        outcomes = iter(after)
        run = Runs(cr.choice_step, "test").run(cr.StartCommand(2.0), cr.ChoiceState())
        action = run.step(cr.Asked(armed, state, airborne, in_air, autopilot))
        while True:
            if isinstance(action, cr.Refuse):
                return [f"refused: {action.reason}"]
            if isinstance(action, cr.TakeOff | cr.TakeControl):
                did.append("takeoff" if isinstance(action, cr.TakeOff) else "control")
                world["state"], world["airborne"] = next(outcomes)
            elif isinstance(action, cr.FlyPending | cr.Resume | cr.Nothing):
                return did + ({cr.FlyPending: ["fly"], cr.Resume: ["resume"]}.get(type(action), []))
            action = run.step(cr.Now(str(world["state"]), bool(world["airborne"]), pending, interrupted))

    assert new() == old()


def _old_brake(flying: bool, fresh: bool, fresh_swaps: bool, prepared: str, prepared_swaps: bool,
               flying_after: bool) -> tuple[str, str] | None:
    """Brakes.brake before the rule: (what it flew, the event's detail), None: returned silently.
    `prepared`: "none", "empty" (a prepared stop without a trajectory) or "stop"."""
    if not flying:
        return None
    why = "fresh message"
    swapped = fresh and fresh_swaps
    which = "fresh"
    if not swapped and prepared == "stop" and prepared_swaps:
        swapped, which, why = True, "prepared", f"{why}; the stop prepared for the braking deadline instead"
    if not swapped:
        if not flying_after:
            return None
        which, why = "hold", f"no verified braking trajectory ({why}); holding at the measured position"
    return which, why


COMBOS = list(itertools.product([False, True], [False, True], [False, True], ["none", "empty", "stop"],
                                [False, True], [False, True]))


def test_brakes_brake_stops_as_the_old_code_did(monkeypatch: pytest.MonkeyPatch) -> None:
    """The real Brakes.brake, every combination of what its planner and the flown plan answer."""
    cfg = Config()
    base = hold(np.array([0.0, 0.0, -1.5]), 0.0)
    stop = hold(np.array([0.0, 0.0, -1.5]), 0.5)

    async def brake_once(combo: tuple[Any, ...]) -> tuple[tuple[str, str] | None, list[Any]]:
        flying, fresh, fresh_swaps, prepared, prepared_swaps, flying_after = combo
        state = {"flying": flying}

        def plan_stop(*_a: Any) -> StopPlan:
            state["flying"] = flying_after  # a pilot may take over while the stop is planned
            return StopPlan(stop if fresh else None, 0.5, "fresh message", True)

        monkeypatch.setattr(braking, "plan_stop", plan_stop)
        flown: list[str] = []

        def swap(traj: Any, start: float, _arrived: Any, _what: str) -> bool:
            flown.append("fresh" if start == 0.5 else "prepared")  # the fresh stop starts at 0.5
            return bool(fresh_swaps if start == 0.5 else prepared_swaps)

        held: list[Any] = []

        class Flown(SimpleNamespace):
            @property
            def flying(self) -> bool:
                return bool(state["flying"])

        control = Flown(committed=lambda: 0.0, now=lambda: 0.0, clock=lambda: (lambda: 0.0), active=base,
                        swap=swap, hold_here=held.append)
        flight = Supervisor(FlightState(State.STREAMING, airborne=True))
        events: list[tuple[str, dict[str, Any]]] = []
        report = SimpleNamespace(event=lambda kind, _msg, **f: events.append((kind, f)))
        steps: list[Any] = []
        runs = braking.choice_runs()
        runs.observe = lambda *call: steps.append(call)
        with ThreadPoolExecutor(1) as pool:
            runtime = SimpleNamespace(loop=asyncio.get_running_loop(), brake_pool=pool)
            brakes = Brakes(cfg, flight, control, runtime, report, lambda: StopContext(None, (), bounds_from(None, cfg)),  # type: ignore[arg-type]
                            lambda: np.zeros(3), runs)
            ready = {"none": None, "empty": StopPlan(None, 0.4, "no stop", False),
                     "stop": StopPlan(stop, 0.4, "prepared message", True)}[prepared]
            await brakes.brake("test", None, prepared=ready)
        if not events:
            return None, steps
        kind, fields = events[-1]
        assert kind == "braking"
        which = "hold" if held else ("prepared" if fields.get("brake_start") == 0.4 else "fresh")
        return (which, fields["detail"]), steps

    for combo in COMBOS:
        got, steps = asyncio.run(brake_once(combo))
        assert got == _old_brake(*combo), combo
        assert steps and all(s[0] == 1 for s in steps)  # one run, shown step by step
        assert [s[1] for s in steps] == list(range(1, len(steps) + 1))


# -- recorded and replayed ------------------------------------------------------------------------


def _recorded(tmp_path: Path) -> Path:
    """Runs of each kind through Runs, as the shells make them, shown to a real Recorder, with the
    planner calls they choose recorded as the Runtime records them (tap.plan)."""
    rec = Recorder(config(tmp_path))
    runs = braking.choice_runs()
    runs.observe = rec.choice_step
    rec.open()

    def planned(fn: Any, ok: bool) -> None:
        t = time.monotonic()
        rec.plan(fn, (), Outcome(ok), t, t + 0.001, "thread")

    # a start: the quick plan infeasible, the search planned
    run = runs.run(cr.StartRules(True, "fastest", False, False), cr.ChoiceState())
    a = run.step(cr.Ask())
    planned(partial(start_mission, quick=True), False)
    a = run.step(cr.Answer(False, INFEASIBLE, "no"))
    assert a == cr.Plan(cr.START)
    planned(partial(start_mission, candidates=12), True)
    run.step(cr.Answer(True, OK, ""))
    # a replan: the local one fails, the remainder is planned
    run = runs.run(cr.ReplanRules(True, True), cr.ChoiceState())
    run.step(cr.Ask())
    planned(local_replan, False)
    run.step(cr.Answer(False, BLOCKED, "blocked"))
    planned(partial(replan_remainder, allocate=True, neighbours=None, candidates=8), True)
    run.step(cr.Answer(True, OK, ""))
    # a stop that holds
    run = runs.run(cr.StopRules(True), cr.ChoiceState())
    run.step(cr.Ask(True))
    run.step(cr.Answer(False, "", "no stop found", True))
    run.step(cr.Answer(False, "", "prepared too late", True))
    # the start command: a take-off, then the mission loaded
    run = runs.run(cr.StartCommand(2.0), cr.ChoiceState())
    assert run.step(cr.Asked(False, "IDLE", False, False, "px4")) == cr.TakeOff(2.0)
    assert run.step(cr.Now("READY", True, True, False)) == cr.FlyPending()
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    return path


@pytest.fixture(scope="module")
def recorded(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _recorded(tmp_path_factory.mktemp("choice"))


def replayed(path: Path) -> tuple[int, str]:
    """What `python -m companion replay` says of the choices (replay_cli runs this; the plans
    recorded here are stand-ins, not replayable calls): whether they differ, and the line."""
    steps, any_ = replay_choice.replay_file(str(path))
    return int(bool(steps.differences)), replay_choice.said(steps, any_)


def test_each_choice_is_recorded_and_replayed_alike(recorded: Path) -> None:
    recs = schema_checked(recorded, TOPIC, "bezier.ChoiceStep")
    assert [r["seq"] for r in recs] == list(range(1, 12))
    assert [(r["call"], r["step"]) for r in recs] == [(c, s) for c in (1, 2, 3) for s in (1, 2, 3)] + [(4, 1), (4, 2)]
    assert [r["rules"]["type"] for r in recs] == ["StartRules"] * 3 + ["ReplanRules"] * 3 + ["StopRules"] * 3 + \
        ["StartCommand"] * 2
    assert recs[8]["action"]["type"] == "Hold" and "prepared" not in recs[8]["action"]["fields"]["detail"]
    code, line = replayed(recorded)
    assert (code, line) == (0, "plan choices: 11 of 11 reproduced (1 replan, 1 start, 1 start command, 1 stop; "
                               "4 planner calls found as chosen; 1 stops held in place)"), line


def test_a_changed_action_and_a_replaced_state_are_named(tmp_path: Path, recorded: Path) -> None:
    def edit(r: dict[str, Any]) -> dict[str, Any]:
        if r["seq"] != 5:
            return r
        return {**r, "action": {"type": "Take", "fields": {"ok": False, "call": cr.LOCAL, "quick": False,
                                                           "detail": ""}}}

    code, line = replayed(rewrite(recorded, tmp_path / "action.mcap", edit, topic=TOPIC))
    assert code == 1 and "first difference: seq 5 (run 2 step 2)" in line and "action" in line, line

    def replaced(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "before": {**r["before"], "quick": True}} if r["seq"] == 3 else r

    code, line = replayed(rewrite(recorded, tmp_path / "state.mcap", replaced, topic=TOPIC))
    assert code == 1 and "seq 3 (run 1 step 3)" in line and "does not start where seq 2 ended" in line, line


def test_a_planner_call_not_made_is_named(tmp_path: Path, recorded: Path) -> None:
    def no_local(r: dict[str, Any]) -> dict[str, Any] | None:
        return None if r["function"] == "companion.mission.local_replan" else r

    code, line = replayed(rewrite(recorded, tmp_path / "plans.mcap", no_local, topic="/planner/plan"))
    assert code == 1 and "seq 4 (run 2 step 1)" in line and "no such planner call" in line, line


def test_a_removed_record_is_a_gap(tmp_path: Path, recorded: Path) -> None:
    code, line = replayed(rewrite(recorded, tmp_path / "gap.mcap", lambda r: None if r["seq"] == 2 else r,
                                  topic=TOPIC))
    assert code == 1 and "seq 2 missing (1 record" in line, line


def test_todays_rule_changed_is_a_difference(recorded: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(cr, "quick_start", lambda rules: False)  # e.g. the anytime start dropped
    code, line = replayed(recorded)
    assert code == 1 and "first difference: seq 1 (run 1 step 1)" in line and "quick" in line, line


def test_a_record_naming_another_class_is_refused(tmp_path: Path, recorded: Path) -> None:
    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "rules": {"type": "Popen", "fields": {"args": ["true"]}}} if r["seq"] == 1 else r

    with pytest.raises(ValueError, match="'Popen' is not a choice's rules"):  # replay_cli: exit 2
        replay_choice.replay_file(str(rewrite(recorded, tmp_path / "foreign.mcap", edit, topic=TOPIC)))
