"""Replay of the plan budget's answers: every /navigator/budget record run through
`companion.plan_budget.budget_step` again.

The budget (companion/plan_budget.py) says how far ahead of now each plan made in flight is
split (a mission's first split, its anytime search's, a replan's, a climb's) and how many
candidate plans a search for the fastest durations may plan before it, from the planning times
measured in this service, into which every plan's time is fed (`Measured`). Each record holds
one question: the budget before, the question (`SplitAhead`, `CandidatesWithin`, `SearchCap`,
`MissionAhead`, `Measured`), the budget after and the answer. Replay runs
`budget_step(rules, before, ask)` again, the rules from the configuration the recording service
ran with, compares the budget after and the answer exactly, and checks:
- the chain: one budget per run, so each record starts where the one before it ended, and the
  run's first record (seq 1) from the budget a service starts with;
- the numbering and the drops the recorder counted (`budget_step`; these share the transitions'
  queue), as for transitions.

So "why did this plan split 2.3 s ahead, and why did its search stop at 6 candidates" is
answered from the file: the planning times measured before it, in order.

A record is JSON only (every value a number, a flag or a string, exact as JSON holds it): it is
read back into the budget's own classes, named in it; a record naming any other is refused.
"""

from __future__ import annotations

import dataclasses
import functools
import typing
from typing import Any

from companion import replay

TOPIC = "/navigator/budget"


@functools.cache
def _asks() -> dict[str, type]:
    from companion import plan_budget

    return {k.__name__: k for k in typing.get_args(plan_budget.Ask)}


def step_values(rec: dict[str, Any]) -> tuple[Any, Any, Any, Any]:
    """(before, ask, after, answer) of a record, typed again from its JSON: the budget's own
    classes only (a record naming another is refused: TypeError, ValueError)."""
    from companion.plan_budget import Budget

    kind = _asks().get(rec["ask"]["type"])
    if kind is None:
        raise ValueError(f"{rec['ask']['type']!r} is not a question to the plan budget")
    return Budget(**rec["before"]), kind(**rec["ask"]["fields"]), Budget(**rec["after"]), rec["answer"]


@dataclasses.dataclass
class BudgetSteps(replay.Chain):
    """What replaying a file's budget records found (replay.Chain), and how many were planning
    times measured into it."""

    measured: int = 0


def replay_steps(recs: list[dict[str, Any]], rules: Any, dropped: int = 0) -> BudgetSteps:
    """Every record (in `seq` order) run again with `rules` (companion.plan_budget.BudgetRules)
    and chained to the one before it."""
    from companion.plan_budget import Budget, Measured, budget_step

    out = BudgetSteps()

    def check(rec: dict[str, Any], previous: tuple[int, Any] | None) -> tuple[Any, list[str]]:
        seq = int(rec["seq"])
        before, ask, after, answer = step_values(rec)
        label = f"seq {seq} {ask!r}"
        why = replay.chained(label, before, previous, "the budget was replaced outside its rule")
        if seq == 1:
            why += replay.compared(label, ("before (the budget a service starts with)", Budget(), before))
        try:
            new, again = budget_step(rules, before, ask)
        except Exception as exc:  # the recorded call returned: raising now is a difference
            return after, [*why, f"{label}: replayed raised {type(exc).__name__}: {exc}"]
        why += replay.compared(label, ("after", after, new), ("answer", answer, again))
        out.measured += isinstance(ask, Measured) and not why
        return after, why

    replay.replay_chain(out, recs, check, dropped, "budget step")
    return out


def replay_file(path: str, since: float | None = None, until: float | None = None) -> tuple[BudgetSteps, bool]:
    """Replay the file's budget records (in the time range); and whether it holds any (a
    record, or a drop counted)."""
    from companion.plan_budget import BudgetRules

    recs, dropped = replay.numbered_records(path, TOPIC, "budget_step", since, until)
    if not recs:
        return replay_steps([], None, dropped), bool(dropped)
    cfg = replay.required_config(path, "answer its plan budget's questions with")
    return replay_steps(recs, BudgetRules.of(cfg), dropped), True


def said(steps: BudgetSteps, recorded: bool) -> str:
    """The replay's line for the budget records."""
    asked = steps.total - steps.measured
    return replay.said_of("budget", steps, recorded,
                          f"{asked} split or search asked, {steps.measured} planning times measured")
