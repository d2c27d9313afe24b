"""Replay of the operator commands' sequences' decisions: every /commands/step record run through
`companion.command_rules.command_step` again.

Each record holds one call of the rules made by a sequence of `Commands` (companion/commands.py:
arm and the OFFBOARD/GUIDED it needs, takeoff and its PX4 climb, land and its wait for the
ground, abort, disarm, and how a command ended): the run's number and the step's within it, the
run's rules (the sequence and its givens), the state before, the observation (the autopilot's
answer or its timeout, the mode and armed state seen, the climb's plan and swap, how the command
ended), the state after and the action. Replay runs `command_step(rules, before, observation)`
again, compares the state after and the action exactly, and checks:
- the chain, per run: its first step starts from the rules' first state, each later one from
  the state the step before it ended in, under the same rules;
- the numbering and the drops the recorder counted (`command_step`; these share the
  transitions' queue), as for transitions;
- with the file's /supervisor/transition records: each transition a step asked for (a
  `Transition`, and `TakeControl`'s ControlTaken) is the transition the step names
  (`transition`: the sequence hands it to the supervisor right after the step), with the same
  event, reason, mode and armed flag.

A record is JSON only (every value a number, a flag or a string, exact as JSON holds it): it is
read back into the rules' own classes, named in it; a record naming any other is refused.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from companion import replay

TOPIC = "/commands/step"


_typed = replay.RulesReader(replay.observations_and_actions("companion.command_rules"),
                             "a command observation or action")


def step_values(rec: dict[str, Any]) -> tuple[Any, Any, Any, Any, Any]:
    """(rules, before, observation, after, action) of a record, typed again from its JSON: the
    rules' own classes only (a record naming another is refused: TypeError, ValueError)."""
    from companion.command_rules import CommandRules, CommandState

    return replay.rule_values(rec, CommandRules, lambda d: CommandState(**d), _typed)


@dataclasses.dataclass
class CommandSteps(replay.Chain):
    """What replaying a file's command steps found (replay.Chain), how many runs finished and
    how many failed, and the transitions the steps made found among the supervisor's."""

    finished: int = 0
    failed: int = 0
    transitions: int = 0
    tied: int = 0


def expected_event(action: Any) -> Any:
    """The supervisor event a step's action makes (None: none)."""
    from companion import supervisor
    from companion.command_rules import EVENTS, TakeControl, Transition

    if isinstance(action, TakeControl):
        return supervisor.ControlTaken()
    if not isinstance(action, Transition):
        return None
    if action.event not in EVENTS:
        raise ValueError(f"{action.event!r} is not an event a command sequence makes")
    kind = getattr(supervisor, action.event)
    given = {"reason": action.reason, "mode": action.mode, "armed": action.armed}
    return kind(**{f.name: given[f.name] for f in dataclasses.fields(kind)})


def _fresh(_rules: Any) -> Any:
    """The state a run starts with."""
    from companion.command_rules import CommandState

    return CommandState()


class _Replayer:
    """Runs the records in `seq` order, chaining each run's steps."""

    def __init__(self, out: CommandSteps, transitions: dict[int, tuple[Any, Any, Any]] | None) -> None:
        self.out = out
        self.transitions = transitions  # the file's transitions by seq (None: not checked)
        self.calls = replay.RunChains(_fresh, "the sequence's state was replaced outside its rules")

    def check(self, rec: dict[str, Any], _previous: tuple[int, Any] | None) -> tuple[Any, list[str]]:
        from companion.command_rules import Fail, Finish, command_step

        seq, call, step = int(rec["seq"]), int(rec["call"]), int(rec["step"])
        rules, before, seen, after, action = step_values(rec)
        label = f"seq {seq} ({rules.sequence}, run {call} step {step}) {seen!r}"
        why, _ = self.calls.chain(label, call, step, seq, rules, before, after, action)
        try:
            new, act = command_step(rules, before, seen)
        except Exception as exc:  # the recorded call returned: raising now is a difference
            return after, [*why, f"{label}: replayed raised {type(exc).__name__}: {exc}"]
        why += replay.compared(label, ("after", after, new), ("action", action, act))
        why += self._transition(label, int(rec["transition"]), action)
        if not why:
            self.out.finished += isinstance(action, Finish)
            self.out.failed += isinstance(action, Fail)
        return after, why

    def _transition(self, label: str, number: int, action: Any) -> list[str]:
        """The transition the action makes is the /supervisor/transition record `number`, alike."""
        if self.transitions is None:
            return []
        try:
            event = expected_event(action)
        except (ValueError, TypeError) as exc:
            return [f"{label}: {exc}"]
        if event is None:
            return []
        self.out.transitions += 1
        found = self.transitions.get(number)
        if found is None:
            return [f"{label}: makes transition {number}, which the file does not hold"]
        if found[1] != event:
            return [f"{label}: transition {number} is {found[1]!r}, the step made {event!r}"]
        self.out.tied += 1
        return []


def replay_steps(recs: list[dict[str, Any]], dropped: int = 0,
                 transitions: list[dict[str, Any]] | None = None) -> CommandSteps:
    """Every record (in `seq` order) run again and chained to the step before it in its run;
    with the file's transition records (None: not checked), each transition made found."""
    out = CommandSteps()
    run = _Replayer(out, None if transitions is None else replay.transitions_by_seq(transitions))
    replay.replay_chain(out, recs, run.check, dropped, "command step")
    return out


def replay_file(path: str, since: float | None = None, until: float | None = None) -> tuple[CommandSteps, bool]:
    """Replay the file's command steps (in the time range), against its transition records (all
    of them: a transition is made just after its step, maybe outside the range); and whether it
    holds any (a record, or a drop counted)."""
    recs, dropped = replay.numbered_records(path, TOPIC, "command_step", since, until)
    transitions, _ = replay.transition_records(path) if recs else ([], 0)
    return replay_steps(recs, dropped, transitions or None), bool(recs) or bool(dropped)


def said(steps: CommandSteps, recorded: bool) -> str:
    """The replay's line for the command steps."""
    return replay.said_of("commands", steps, recorded,
                          f"{steps.finished} runs finished, {steps.failed} failed; {steps.tied} of {steps.transitions} "
                          "transitions found as made")
