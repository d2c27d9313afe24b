"""A mission sent in flight from a split where nothing plans: the start tried further along the
flown plan (companion.choice_rules `StartRules.later`, MissionStart.fly's plan_at).

From a few moving jets no degree-9 first segment reaches the mission's first waypoint within the
bounds, whatever its duration or lead knot (planner_core.missions.lead_in), and a mission sent
then was refused (a CI failure of test_missions_replaced_in_flight_are_all_flown: m5-5 sent while
m4-20 flew). The rule: from a moving split, an infeasible start is tried again from the flown
plan 0.25 s and 0.5 s later (the flown plan flies on until then); from rest, or for any other
refusal, it is not. The real planner calls from the real failing jets: each split where the
start from the jet is refused plans with a later start, and the splice passes the swap's own
rule at the split and the verifier."""

from __future__ import annotations

import sys
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from companion import choice_rules as cr
from companion.config import Config
from companion.control import jet_on, swap_refusal
from companion.limits import clip_bounds, limits_from_params
from companion.mission import start_mission
from companion.mission_start import LATER_START
from companion.rule_run import Runs
from companion.wire.messages import MissionSpec, read
from planner_core import rest_jet, splice, verify

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "mock"))
INFEASIBLE = "INFEASIBLE"


def _run(rules: cr.StartRules) -> Any:
    return Runs(cr.choice_step, "test").run(rules, cr.ChoiceState())


def _calls(rules: cr.StartRules, moving: bool, answers: list[tuple[bool, str]]) -> tuple[list[cr.Plan], cr.Take]:
    """The plans one attempt asks for, given the planner's answers in turn, and what it takes."""
    run = _run(rules)
    action = run.step(cr.Ask(moving=moving))
    plans: list[cr.Plan] = []
    it = iter(answers)
    while isinstance(action, cr.Plan):
        plans.append(action)
        ok, status = next(it)
        action = run.step(cr.Answer(ok, status, "m"))
    assert isinstance(action, cr.Take)
    return plans, action


def test_an_infeasible_moving_start_is_tried_twice_further_along_the_flown_plan() -> None:
    quick = cr.StartRules(True, "fastest", False, False, 0.25)
    plans, take = _calls(quick, True, [(False, INFEASIBLE)] * 4)
    assert [(p.quick, p.later) for p in plans] == [(True, 0.0), (False, 0.0), (False, 0.25), (False, 0.5)]
    assert not take.ok and not take.quick
    plans, take = _calls(quick, True, [(False, INFEASIBLE), (False, INFEASIBLE), (True, "OK")])
    assert plans[-1].later == 0.25 and take.ok and not take.quick  # the search's plan flies: no improvement
    timed = cr.StartRules(True, "fastest", True, False, 0.25)
    plans, take = _calls(timed, True, [(False, INFEASIBLE), (False, INFEASIBLE), (True, "OK")])
    assert [(p.call, p.quick, p.later) for p in plans] == [(cr.START, False, 0.0), (cr.START, False, 0.25),
                                                          (cr.START, False, 0.5)]
    fleet = cr.StartRules(True, "fastest", False, True, 0.25)
    plans, _ = _calls(fleet, True, [(False, INFEASIBLE)] * 3)
    assert [(p.call, p.later) for p in plans] == [(cr.SEPARATED, 0.0), (cr.SEPARATED, 0.25), (cr.SEPARATED, 0.5)]


@pytest.mark.parametrize(("moving", "status", "later"), [(False, INFEASIBLE, 0.25), (True, "BLOCKED", 0.25),
                                                         (True, INFEASIBLE, 0.0)])
def test_no_later_start_from_rest_for_other_refusals_or_when_off(moving: bool, status: str, later: float) -> None:
    plans, take = _calls(cr.StartRules(False, "fastest", False, False, later), moving, [(False, status)])
    assert [p.later for p in plans] == [0.0] and not take.ok


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.booleans(), st.sampled_from([INFEASIBLE, "BLOCKED"])), min_size=12, max_size=12),
       st.booleans(), st.integers(1, 3))
def test_each_attempt_of_the_split_loop_starts_at_the_split(answers: list[tuple[bool, str]], anytime: bool,
                                                             tries: int) -> None:
    """Whatever the answers: every attempt's first call is at the split, later starts only follow
    an infeasible answer, each 0.25 s further, at most two."""
    run = _run(cr.StartRules(anytime, "fastest", False, False, 0.25))
    it = iter(answers)
    for _ in range(tries):
        action = run.step(cr.Ask(moving=True))
        assert isinstance(action, cr.Plan) and action.later == 0.0
        previous = 0.0
        while isinstance(action, cr.Plan):
            assert action.later in (previous, previous + 0.25) and action.later <= 0.5
            previous = action.later
            ok, status = next(it)
            action = run.step(cr.Answer(ok, status, "m"))
            if isinstance(action, cr.Plan) and action.later > previous:
                assert not ok and status == INFEASIBLE


# -- the real planner on the jets that failed ------------------------------------------------------


def _spec(mid: str, n: int, phase: float, cfg: Config) -> MissionSpec:
    from test_missions_in_flight import mission  # the CI failure's missions, as it sends them

    spec = read("mission", mission(mid, n, phase), cfg)
    assert isinstance(spec, MissionSpec)
    bounds, _ = clip_bounds(spec.bounds, limits_from_params("px4", {}), 0.9)  # as the mock PX4's limits clip them
    return replace(spec, bounds=bounds)


def _start(spec: MissionSpec, base: Any, t_split: float, cfg: Config) -> tuple[Any, float]:
    """The start as MissionStart.fly's plan_at asks the rule and plans (no budget cap): the
    outcome and how far past the split it starts."""
    run = _run(cr.StartRules(cfg.planner.anytime, cfg.planner.timing, False, False, LATER_START))
    jet = jet_on(base, t_split)
    action = run.step(cr.Ask(moving=bool(np.any(jet[1:] != 0.0))))
    while True:
        assert isinstance(action, cr.Plan)
        fn: Any = partial(start_mission, quick=True) if action.quick else start_mission
        at = t_split + action.later
        out = fn(replace(spec, raw={}), jet_on(base, at) if action.later else jet, at, [], cfg)
        action = run.step(cr.Answer(out.ok, out.status.name, out.message))
        if isinstance(action, cr.Take):
            return out, at - t_split


def test_missions_refused_from_the_jet_plan_from_a_later_start() -> None:
    cfg = Config()
    m3, m4, m5 = (_spec(f"m{i}-{n}", n, 0.7 * i, cfg) for i, n in ((3, 300), (4, 20), (5, 5)))
    flown3 = start_mission(m3, rest_jet(np.array([-5.6, 1.0, -2.0])), 0.0, [], cfg, quick=True)
    assert flown3.ok and flown3.route is not None
    quick = start_mission(m4, flown3.route.trajectory.jet(2.5), 2.5, [], cfg, quick=True)  # m4 sent 2.5 s into m3
    assert quick.ok and quick.route is not None
    base = quick.route.trajectory
    later_starts = 0
    for t in (4.8, 4.85, 4.9, 4.95):  # m5 sent 2.3-2.45 s into m4
        out, later = _start(m5, base, t, cfg)
        assert out.ok and out.route is not None, f"m5 from t={t:.2f}: {out.message}"
        later_starts += later > 0.0  # by the rule, only after the quick plan and the search at t failed
        flown = splice(base, out.route.trajectory)
        # the swap's own rule, decided 0.2 s before the split with the setpoints 0.1 s ahead
        assert swap_refusal(base, flown, t - 0.2, 0.1, 50.0, t) == ""
        report = verify(out.route.trajectory, out.route.problem)
        assert report.ok, report.summary()
        assert np.allclose(flown.jet(t + later), jet_on(base, t + later), atol=1e-6)
    # these splits are ones the jet alone cannot start from (else this test tests nothing)
    assert later_starts >= 3, later_starts
