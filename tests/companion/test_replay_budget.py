"""The plan budget's one rule (companion.plan_budget.budget_step) and its replay.

The rule answers as the budget's methods did before it was one pure function (an oracle copy of
that code, on generated question sequences); a real PlanBudget wired to a real Recorder writes
every question into a real MCAP file, which replay answers again alike (exit 0); a changed
answer, a changed budget, a removed or dropped record and today's rule changed are each named by
their seq (exit 1); a record naming another class is refused (exit 2)."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from recorder_support import config, schema_checked
from test_replay_transitions import rewrite

from companion import plan_budget, replay_cli
from companion.plan_budget import (
    FIXED_WAYPOINTS,
    FULL_SEARCH,
    LATE_MARGIN,
    MAX_AHEAD,
    MIN_CANDIDATES,
    Budget,
    BudgetRules,
    CandidatesWithin,
    Measured,
    MissionAhead,
    PlanBudget,
    SearchCap,
    SplitAhead,
    budget_step,
)
from companion.recorder import Recorder

TOPIC = "/navigator/budget"


class _OldBudget:
    """The budget's methods as they were before the rule (verbatim but for `cfg`): the oracle."""

    def __init__(self, split_ahead: float, search_time: float) -> None:
        self.split_ahead, self.search_time = split_ahead, search_time
        self.per_waypoint = 0.004

    def candidate_seconds(self, n_waypoints: int) -> float:
        return self.per_waypoint * (max(n_waypoints, 1) + FIXED_WAYPOINTS)

    def split_ahead_for(self, n_waypoints: int, candidates: int = 1) -> float:
        expect = self.candidate_seconds(n_waypoints) * max(candidates, 1)
        return float(min(max(self.split_ahead, LATE_MARGIN * expect + 0.05), MAX_AHEAD))

    def candidates_within(self, n_waypoints: int, seconds: float) -> int | None:
        k = int(max(seconds - 0.05, 0.0) / LATE_MARGIN / self.candidate_seconds(n_waypoints))
        return None if k >= FULL_SEARCH else max(k, MIN_CANDIDATES)

    def search_cap(self, n_waypoints: int) -> int:
        fit = int(self.search_time / self.candidate_seconds(n_waypoints))
        return min(max(fit, MIN_CANDIDATES), FULL_SEARCH)

    def mission_ahead(self, n_waypoints: int) -> float:
        return self.split_ahead_for(n_waypoints, self.search_cap(n_waypoints))

    def measured(self, seconds: float, n_waypoints: int, candidates: int = 1) -> None:
        per = seconds / max(candidates, 1) / (max(n_waypoints, 1) + FIXED_WAYPOINTS)
        a = 1.0 if per > self.per_waypoint else 0.2
        self.per_waypoint = (1 - a) * self.per_waypoint + a * per


waypoints = st.integers(0, 2000)
asks = st.one_of(
    st.builds(SplitAhead, waypoints, st.integers(0, 60)),
    st.builds(CandidatesWithin, waypoints, st.floats(-1.0, 40.0)),
    st.builds(SearchCap, waypoints),
    st.builds(MissionAhead, waypoints),
    st.builds(Measured, st.floats(1e-5, 20.0), waypoints, st.integers(0, 60)),
)


def _old_answer(old: _OldBudget, ask: Any) -> Any:
    if isinstance(ask, SplitAhead):
        return old.split_ahead_for(ask.n_waypoints, ask.candidates)
    if isinstance(ask, CandidatesWithin):
        return old.candidates_within(ask.n_waypoints, ask.seconds)
    if isinstance(ask, SearchCap):
        return old.search_cap(ask.n_waypoints)
    if isinstance(ask, MissionAhead):
        return old.mission_ahead(ask.n_waypoints)
    return old.measured(ask.seconds, ask.n_waypoints, ask.candidates)


@settings(max_examples=200, deadline=None)
@given(st.floats(0.05, 5.0), st.floats(0.01, 10.0), st.lists(asks, max_size=30))
def test_the_rule_answers_as_the_methods_did(split_ahead: float, search_time: float, seq: list[Any]) -> None:
    old, rules, budget = _OldBudget(split_ahead, search_time), BudgetRules(split_ahead, search_time), Budget()
    for ask in seq:
        budget, answer = budget_step(rules, budget, ask)
        assert answer == _old_answer(old, ask) and budget.per_waypoint == old.per_waypoint, ask
        if isinstance(ask, Measured):
            assert answer is None
        elif isinstance(ask, SplitAhead | MissionAhead):  # never nearer than split_ahead, nor beyond MAX_AHEAD
            assert answer == min(max(answer, split_ahead), MAX_AHEAD)
        elif isinstance(ask, SearchCap):
            assert MIN_CANDIDATES <= answer <= FULL_SEARCH


def _recorded(tmp_path: Path, asks_made: list[Any]) -> tuple[Path, list[tuple[Any, Any]]]:
    """A real PlanBudget shown to a real Recorder: each question asked, the file written."""
    cfg = config(tmp_path)
    rec = Recorder(cfg)
    budget = PlanBudget(cfg)
    budget.observe = rec.budget_step
    rec.open()
    answers = []
    for ask in asks_made:
        answers.append((ask, plan_budget.budget_step(budget.rules, budget.state, ask)[1]))
        if isinstance(ask, SplitAhead):
            assert budget.split_ahead_for(ask.n_waypoints, ask.candidates) == answers[-1][1]
        elif isinstance(ask, CandidatesWithin):
            assert budget.candidates_within(ask.n_waypoints, ask.seconds) == answers[-1][1]
        elif isinstance(ask, SearchCap):
            assert budget.search_cap(ask.n_waypoints) == answers[-1][1]
        elif isinstance(ask, MissionAhead):
            assert budget.mission_ahead(ask.n_waypoints) == answers[-1][1]
        else:
            budget.measured(ask.seconds, ask.n_waypoints, ask.candidates)
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    return path, answers


# a service's questions: the warm-up's time, a mission's first split and its search, its plan's
# time (slow: the estimate goes up at once), the anytime search, a replan, a fast plan (down slowly)
FLIGHT = [Measured(0.06, 2), MissionAhead(12), CandidatesWithin(12, 1.2), Measured(3.0, 12, 8), SearchCap(12),
          SplitAhead(12, 7), Measured(0.2, 12, 7), CandidatesWithin(9, 0.4), Measured(0.01, 9), SplitAhead(2)]


@pytest.fixture(scope="module")
def flown(tmp_path_factory: pytest.TempPathFactory) -> Path:
    return _recorded(tmp_path_factory.mktemp("budget"), FLIGHT)[0]


def run(path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = replay_cli.main([str(path)])
    return code, next(ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("budget:"))


def test_every_question_is_recorded_in_order_and_answered_alike(tmp_path: Path,
                                                               capsys: pytest.CaptureFixture[str]) -> None:
    path, answers = _recorded(tmp_path, FLIGHT)
    recs = schema_checked(path, TOPIC, "bezier.BudgetStep")
    assert [r["seq"] for r in recs] == list(range(1, len(FLIGHT) + 1))
    assert [(r["ask"]["type"], r["answer"]) for r in recs] == [(type(a).__name__, x) for a, x in answers]
    # the budget went up at once on the slow plan and down slowly after the fast one
    per = [r["after"]["per_waypoint"] for r in recs]
    assert per[3] > per[2] and per[0] < per[3] and per[8] < per[7] and per[8] > 0.01 / (9 + FIXED_WAYPOINTS)
    assert run(path, capsys) == (0, f"budget: {len(FLIGHT)} of {len(FLIGHT)} reproduced (6 split or search asked, "
                                    "4 planning times measured)")


def test_a_changed_answer_is_named(tmp_path: Path, flown: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "answer": r["answer"] + 1} if r["seq"] == 3 else r

    code, line = run(rewrite(flown, tmp_path / "answer.mcap", edit, topic=TOPIC), capsys)
    assert code == 1 and line.startswith("budget: 9 of 10 reproduced; first difference: seq 3 CandidatesWithin("), line
    assert "answer" in line


def test_a_budget_replaced_outside_the_rule_is_named(tmp_path: Path, flown: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """A record that starts from another budget than the one before it ended in (the chain)."""
    def edit(r: dict[str, Any]) -> dict[str, Any]:
        if r["seq"] != 5:
            return r
        changed = {"per_waypoint": r["before"]["per_waypoint"] * 2}
        return {**r, "before": changed, "after": changed}

    code, line = run(rewrite(flown, tmp_path / "chain.mcap", edit, topic=TOPIC), capsys)
    assert code == 1 and "seq 5 SearchCap(" in line and "does not start where seq 4 ended" in line, line


def test_a_first_record_not_from_a_fresh_budget_is_named(tmp_path: Path, flown: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "before": {"per_waypoint": 0.01}} if r["seq"] == 1 else r

    code, line = run(rewrite(flown, tmp_path / "first.mcap", edit, topic=TOPIC), capsys)
    assert code == 1 and "seq 1 Measured(" in line and "the budget a service starts with" in line, line


def test_a_removed_record_is_a_gap(tmp_path: Path, flown: Path, capsys: pytest.CaptureFixture[str]) -> None:
    code, line = run(rewrite(flown, tmp_path / "gap.mcap", lambda r: None if r["seq"] == 4 else r, topic=TOPIC),
                     capsys)
    assert code == 1 and "seq 4 missing (1 record" in line, line


def test_records_the_recorder_dropped_are_counted(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A queue of 2 before the writer starts: the questions past it are dropped, counted, named."""
    cfg = config(tmp_path, queue=2)
    rec = Recorder(cfg)
    budget = PlanBudget(cfg)
    budget.observe = rec.budget_step
    for ask in FLIGHT[:6]:
        budget.measured(0.05, 3) if isinstance(ask, Measured) else budget.search_cap(5)
    rec.open()
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    code, line = run(path, capsys)
    assert code == 1 and line == ("budget: 2 of 2 reproduced; first difference: the recorder dropped 4 budget step "
                                  "records in this run (its queue was full): the chain is not checkable across them")


def test_todays_rule_changed_is_a_difference(flown: Path, capsys: pytest.CaptureFixture[str],
                                             monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(plan_budget, "LATE_MARGIN", LATE_MARGIN * 2)
    code, line = run(flown, capsys)
    assert code == 1 and "first difference: seq 2 MissionAhead(" in line, line


def test_a_record_cannot_name_another_class(tmp_path: Path, flown: Path) -> None:
    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "ask": {"type": "Braking", "fields": {"reason": "x"}}} if r["seq"] == 2 else r

    assert replay_cli.main([str(rewrite(flown, tmp_path / "other.mcap", edit, topic=TOPIC))]) == 2


def test_records_are_json_only(flown: Path) -> None:
    """Every value a number, a string or null: nothing a viewer cannot show, nothing to unpickle."""
    recs = schema_checked(flown, TOPIC, "bezier.BudgetStep")
    assert all(set(r) == {"seq", "t", "before", "ask", "after", "answer"} for r in recs)
    assert json.loads(json.dumps(recs)) == recs
