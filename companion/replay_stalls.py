"""Replay of the stall watch's decisions: every /stalls/step record run through
`companion.stall_rules.stall_step` again.

Each record holds one call of the rules by `StallWatch.loop_liveness` (companion/stalls.py) that
changed their state (the flight state before any stall, which the `stalled` event names), found
a stall, or settled after one (or at the start): the rules (`[setpoints] loop_stall_limit`, STALL_HOLD_WITHIN), the state before, the
observation (a beat of the loop: its gap, the setpoint sender's latch, the time since a setpoint
left, control, the flight state; or the flight state once a stall was dealt with), the state
after and the action (quiet, or the stall and what follows: nothing when not in control, hold,
or release control). Quiet beats that change nothing are not recorded: the state they leave is
the one they found. Replay runs `stall_step(rules, before, observation)` again, compares the
state after and the action exactly, and checks:
- the chain: one watch per run, so each record starts where the one before it ended, under the
  same rules, and the run's first record (seq 1) from the state a watch starts with;
- the numbering and the drops the recorder counted (`stall_step`; these share the transitions'
  queue), as for transitions;
- that a stall is followed by the watch's `Settled` (the stall dealt with; always recorded) before
  the next beat.

So "why did the companion hold (or release control) here, and what was it doing before" is
answered from the file: the beat that found the stall, and how long setpoints had been withheld.

A record is JSON only: it is read back into the rules' own classes, named in it; a record naming
any other is refused.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from companion import replay

TOPIC = "/stalls/step"

_typed = replay.RulesReader(replay.observations_and_actions("companion.stall_rules"), "a stall observation or action")


def step_values(rec: dict[str, Any]) -> tuple[Any, Any, Any, Any, Any]:
    """(rules, before, observation, after, action) of a record, typed again from its JSON: the
    rules' own classes only (a record naming another is refused: TypeError, ValueError)."""
    from companion.stall_rules import StallRules, StallState

    return replay.rule_values(rec, StallRules, lambda d: StallState(**d), _typed)


@dataclasses.dataclass
class StallSteps(replay.Chain):
    """What replaying a file's stall records found (replay.Chain), and the stalls among them by
    what the watch did about each."""

    held: int = 0
    released: int = 0
    not_in_control: int = 0


class _Replayer:
    def __init__(self, out: StallSteps) -> None:
        self.out = out
        self.rules: Any = None
        self.stalled: int | None = None  # seq of a stall not yet followed by its Settled

    def check(self, rec: dict[str, Any], previous: tuple[int, Any] | None) -> tuple[Any, list[str]]:
        from companion.stall_rules import Settled, Stalled, StallState, stall_step

        seq = int(rec["seq"])
        rules, before, seen, after, action = step_values(rec)
        label = f"seq {seq} {seen!r}"
        why = replay.chained(label, before, previous, "the watch's state was replaced outside its rules")
        if seq == 1:
            why += replay.compared(label, ("before (the state a watch starts with)", StallState(), before))
        elif self.rules is not None:
            why += replay.compared(label, ("rules", self.rules, rules))
        self.rules = rules
        if self.stalled is not None and not isinstance(seen, Settled) and previous is not None \
                and previous[0] == self.stalled:
            why.append(f"{label}: the stall at seq {self.stalled} was not dealt with (no Settled) before this beat")
        self.stalled = seq if isinstance(action, Stalled) else None
        try:
            new, act = stall_step(rules, before, seen)
        except Exception as exc:  # the recorded call returned: raising now is a difference
            return after, [*why, f"{label}: replayed raised {type(exc).__name__}: {exc}"]
        why += replay.compared(label, ("after", after, new), ("action", action, act))
        if not why and isinstance(action, Stalled):
            self.out.held += action.reaction == "hold"
            self.out.released += action.reaction == "release"
            self.out.not_in_control += action.reaction == "none"
        return after, why


def replay_steps(recs: list[dict[str, Any]], dropped: int = 0) -> StallSteps:
    """Every record (in `seq` order) run again and chained to the one before it."""
    out = StallSteps()
    replay.replay_chain(out, recs, _Replayer(out).check, dropped, "stall step")
    return out


def replay_file(path: str, since: float | None = None, until: float | None = None) -> tuple[StallSteps, bool]:
    """Replay the file's stall records (in the time range); and whether it holds any (a record,
    or a drop counted)."""
    recs, dropped = replay.numbered_records(path, TOPIC, "stall_step", since, until)
    return replay_steps(recs, dropped), bool(recs) or bool(dropped)


def said(steps: StallSteps, recorded: bool) -> str:
    """The replay's line for the stall records."""
    stalls = steps.held + steps.released + steps.not_in_control
    return replay.said_of("stalls", steps, recorded,
                          f"{stalls} stalls: {steps.held} held, {steps.released} released control, "
                          f"{steps.not_in_control} not in control")
