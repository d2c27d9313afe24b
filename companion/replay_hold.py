"""Replay of the hand-over's hold confirmations: every /handover/hold record run through
`companion.hold_rules.hold_step` again.

Each record holds one call of the rules while `HandOver._confirm_hold` (companion/handover.py)
watched the vehicle after handing it to an autonomous hold: the hold's number and the step's
within it, the rules (the autopilot's hold profile: altitude and speed tolerances, settle and
confirm times), the state before, the observation (where the hold began, or a sample of the
vehicle: armed, mode, altitude, velocity), the state after and the action (watch on, holds,
fails and why). Replay runs `hold_step(rules, before, observation)` again, compares the state
after and the action exactly, and checks:
- the chain, per hold: its first step (`Began`) from the state a watch starts with, each later
  one from the state the step before it ended in, under the same rules; a hold's steps end with
  its verdict (nothing after `Holds` or `Fails`);
- the numbering and the drops the recorder counted (`hold_step`; these share the transitions'
  queue), as for transitions.

So "why did the companion say the autopilot holds the vehicle" (or that it does not) is answered
from the file: every sample it judged, against the profile it judged them by.

A record is JSON only: it is read back into the rules' own classes, named in it; a record naming
any other is refused.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from companion import replay

TOPIC = "/handover/hold"

_typed = replay.RulesReader(replay.observations_and_actions("companion.hold_rules"), "a hold observation or action",
                            tuples=("velocity",))


def step_values(rec: dict[str, Any]) -> tuple[Any, Any, Any, Any, Any]:
    """(rules, before, observation, after, action) of a record, typed again from its JSON: the
    rules' own classes only (a record naming another is refused: TypeError, ValueError)."""
    from companion.hold_rules import HoldRules, HoldState

    return replay.rule_values(rec, HoldRules, lambda d: HoldState(**d), _typed)


@dataclasses.dataclass
class HoldSteps(replay.Chain):
    """What replaying a file's hold records found (replay.Chain), and the verdicts among them."""

    held: int = 0
    failed: int = 0


def _fresh(_rules: Any) -> Any:
    """The state a run starts with."""
    from companion.hold_rules import HoldState

    return HoldState()


class _Replayer:
    def __init__(self, out: HoldSteps) -> None:
        self.out = out
        self.calls = replay.RunChains(_fresh, "the hold's state was replaced outside its rules",
                                      "before (the state a watch starts with)")

    def check(self, rec: dict[str, Any], _previous: tuple[int, Any] | None) -> tuple[Any, list[str]]:
        from companion.hold_rules import Fails, Holds, hold_step

        seq, call, step = int(rec["seq"]), int(rec["call"]), int(rec["step"])
        rules, before, seen, after, action = step_values(rec)
        label = f"seq {seq} (hold {call} step {step}) {seen!r}"
        why, last = self.calls.chain(label, call, step, seq, rules, before, after, action)
        if last is not None and isinstance(last.action, Holds | Fails):
            why.append(f"{label}: follows the verdict of step {last.step} ({last.action!r})")
        try:
            new, act = hold_step(rules, before, seen)
        except Exception as exc:  # the recorded call returned: raising now is a difference
            return after, [*why, f"{label}: replayed raised {type(exc).__name__}: {exc}"]
        why += replay.compared(label, ("after", after, new), ("action", action, act))
        if not why:
            self.out.held += isinstance(action, Holds)
            self.out.failed += isinstance(action, Fails)
        return after, why


def replay_steps(recs: list[dict[str, Any]], dropped: int = 0) -> HoldSteps:
    """Every record (in `seq` order) run again and chained to the step before it in its hold."""
    out = HoldSteps()
    replay.replay_chain(out, recs, _Replayer(out).check, dropped, "hold step")
    return out


def replay_file(path: str, since: float | None = None, until: float | None = None) -> tuple[HoldSteps, bool]:
    """Replay the file's hold records (in the time range); and whether it holds any (a record, or
    a drop counted)."""
    recs, dropped = replay.numbered_records(path, TOPIC, "hold_step", since, until)
    return replay_steps(recs, dropped), bool(recs) or bool(dropped)


def said(steps: HoldSteps, recorded: bool) -> str:
    """The replay's line for the hold records."""
    return replay.said_of("holds", steps, recorded, f"{steps.held} held, {steps.failed} not held")
