"""Replay of the navigator's plan choices: every /navigator/choice record run through
`companion.choice_rules.choice_step` again, and each planner call it chose found in the file.

Each record holds one call of the rules while a mission started (companion/mission_start.py),
the flown mission was replanned (companion/replans.py), a stop was made (companion/braking.py
`Brakes.brake`), a quick start was improved (`MissionStart.improve`) or the `start` command chose what to do first and what to fly
(companion/commands.py): the run's number and the step's within it, the rules
(a start's, a replan's or a stop's givens), the state before, the observation (the run asks,
or the answer of the call made: ok, status, message, whether the vehicle is still flown), the
state after and the action (the call to make, the answer that stands, hold, nothing). Replay
runs `choice_step(rules, before, observation)` again, compares the state after and the action
exactly, and checks:
- the chain, per run: its first step from the state a run starts with, each later one from
  the state the step before it ended in, under the same rules; nothing after a run's last word
  (an answer taken, hold, nothing, a refusal, fly or resume) but a new ask of the same run (the
  split loop's retry);
- that each planner call chosen was made: a /planner/plan record of that function (and its
  `quick` or `allocate` argument) submitted after the choice and before the run's next step
  (a stop is planned in the brake thread, which records no plan: its swap is in /control/swap);
- the numbering and the drops the recorder counted (`choice_step`), as for transitions.

So "why did the companion plan this mission on the default durations" (or "why did it hold
instead of braking on a stop") is answered from the file.

A record is JSON only: it is read back into the rules' own classes, named in it; a record naming
any other is refused.
"""

from __future__ import annotations

import bisect
import dataclasses
from typing import Any

from companion import replay

TOPIC = "/navigator/choice"

_typed = replay.RulesReader(replay.observations_and_actions("companion.choice_rules"), "a choice observation or action")


def _rules_kinds() -> tuple[type, ...]:
    import typing

    from companion import choice_rules

    return typing.get_args(choice_rules.Rules)


_rules = replay.RulesReader(_rules_kinds, "a choice's rules")


def step_values(rec: dict[str, Any]) -> tuple[Any, Any, Any, Any, Any]:
    """(rules, before, observation, after, action) of a record, typed again from its JSON: the
    rules' own classes only (a record naming another is refused: TypeError, ValueError)."""
    from companion.choice_rules import ChoiceState

    return (_rules(rec["rules"]), ChoiceState(**rec["before"]), _typed(rec["observation"]),
            ChoiceState(**rec["after"]), _typed(rec["action"]))


def made_by(name: str, action: Any) -> bool:
    """The plan record's function `name` is the call `action` (a Plan) asked for."""
    from companion import choice_rules as cr

    call: str = action.call
    if call == cr.START:
        if action.quick:
            return name == f"{call}(quick=True)"
        return name == call or name.startswith(f"{call}(candidates=")
    if call == cr.REMAINDER:
        given = f"{call}(allocate={bool(action.allocate)}"
        return name == f"{given})" or name.startswith(f"{given},")
    if call == cr.SEPARATED:
        return name.startswith(f"{call}(")
    return name == call


@dataclasses.dataclass
class ChoiceSteps(replay.Chain):
    """What replaying a file's choice records found (replay.Chain), and what was chosen."""

    calls: int = 0  # planner calls chosen and found in the file
    runs: dict[str, int] = dataclasses.field(default_factory=dict)  # runs by kind: start, replan, stop
    held: int = 0  # stops that held at the measured position


def _fresh(_rules: Any) -> Any:
    """The state a run starts with."""
    from companion.choice_rules import ChoiceState

    return ChoiceState()


class _Replayer:
    def __init__(self, out: ChoiceSteps, plans: list[tuple[float, float, str]] | None,
                 next_t: dict[int, float]) -> None:
        self.out = out
        self.runs = replay.RunChains(_fresh, "the run's state was replaced outside its rules",
                                     "before (the state a run starts with)")
        self.plans = plans  # (submitted, done, function) of the file's plan records, by submitted; None: not checked
        self.claimed: set[int] = set()
        self.next_t = next_t  # seq -> t of the run's next step (absent: the run's last)

    def _made(self, rec: dict[str, Any], action: Any, label: str) -> list[str]:
        from companion import choice_rules as cr

        if self.plans is None or not isinstance(action, cr.Plan) or action.call in (cr.STOP, cr.PREPARED):
            return []
        t, until = float(rec["t"]), self.next_t.get(int(rec["seq"]), float("inf"))
        i = bisect.bisect_left(self.plans, (t,))
        while i < len(self.plans) and self.plans[i][0] <= until:
            if i not in self.claimed and made_by(self.plans[i][2], action):
                self.claimed.add(i)
                self.out.calls += 1
                return []
            i += 1
        return [f"{label}: chose {action!r}, but the file holds no such planner call before the run's next step"]

    def check(self, rec: dict[str, Any], _previous: tuple[int, Any] | None) -> tuple[Any, list[str]]:
        from companion import choice_rules as cr

        seq, run, step = int(rec["seq"]), int(rec["call"]), int(rec["step"])
        rules, before, seen, after, action = step_values(rec)
        label = f"seq {seq} (run {run} step {step}) {seen!r}"
        why, last = self.runs.chain(label, run, step, seq, rules, before, after, action)
        if step == 1:
            kind = {cr.StartRules: "start", cr.ReplanRules: "replan", cr.StopRules: "stop",
                    cr.StartCommand: "start command", cr.ImproveRules: "improvement"}[type(rules)]
            self.out.runs[kind] = self.out.runs.get(kind, 0) + 1
        final = cr.Take | cr.Hold | cr.Nothing | cr.Refuse | cr.FlyPending | cr.Resume
        if last is not None and isinstance(last.action, final) and not isinstance(seen, cr.Ask):
            why.append(f"{label}: an answer after the run's last word at step {last.step} ({last.action!r})")
        try:
            new, act = cr.choice_step(rules, before, seen)
        except Exception as exc:  # the recorded call returned: raising now is a difference
            return after, [*why, f"{label}: replayed raised {type(exc).__name__}: {exc}"]
        why += replay.compared(label, ("after", after, new), ("action", action, act))
        why += self._made(rec, action, label)
        if not why:
            self.out.held += isinstance(action, cr.Hold)
        return after, why


def replay_steps(recs: list[dict[str, Any]], dropped: int = 0,
                 plans: list[tuple[float, float, str]] | None = None) -> ChoiceSteps:
    """Every record (in `seq` order) run again and chained to the step before it in its run;
    with `plans` ((submitted, done, function) of the plan records), each call chosen looked for."""
    out = ChoiceSteps()
    next_t: dict[int, float] = {}
    last: dict[int, int] = {}
    for rec in sorted(recs, key=lambda r: int(r["seq"])):
        run = int(rec["call"])
        if run in last:
            next_t[last[run]] = float(rec["t"])
        last[run] = int(rec["seq"])
    replay.replay_chain(out, recs, _Replayer(out, None if plans is None else sorted(plans), next_t).check,
                        dropped, "choice step")
    return out


def replay_file(path: str, since: float | None = None, until: float | None = None) -> tuple[ChoiceSteps, bool]:
    """Replay the file's choice records (in the time range) against its plan records; and
    whether it holds any (a record, or a drop counted)."""
    recs, dropped = replay.numbered_records(path, TOPIC, "choice_step", since, until)
    plans = [(float(p["submitted"]), float(p["done"]), str(p["function"]))
             for _n, _rel, p in replay.records(path, ("/planner/plan",))]
    return replay_steps(recs, dropped, plans), bool(recs) or bool(dropped)


def said(steps: ChoiceSteps, recorded: bool) -> str:
    """The replay's line for the choice records."""
    runs = ", ".join(f"{n} {k}{'s' * (n > 1)}" for k, n in sorted(steps.runs.items())) or "no run begun"
    return replay.said_of("plan choices", steps, recorded,
                          f"{runs}; {steps.calls} planner calls found as chosen; {steps.held} stops held in place")
