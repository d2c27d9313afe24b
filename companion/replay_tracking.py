"""Replay of the tracking error's rules: every /tracking/step record run through
`companion.tracking_rules.tracking_step` again, and each brake it asked for found among the
supervisor's transitions.

Each record holds one call that changed the rules' state or said something (a call that did
neither, most of them on the ground, is not recorded): the state before and after as
`StateSeen` (the window of recent errors by its length and CRC-32, not the 150 numbers), the
reading (the error, whether a plan of ours is flown, the limit and its name, the allowance,
whether the last tracking stop still runs) and the outputs. The window is rebuilt from the
records' readings in order; the recorder writes it in full in the first record of a file and
after a gap (a `keyframe`), so that replay can start there. Replay runs
`tracking_step(rules, before, reading)` again, the rules from the configuration the recording
service ran with, compares the state after and the outputs exactly, and checks:
- the chain, the numbering and the drops the recorder counted (`tracking_step`; these share the
  transitions' queue), as for transitions;
- with the file's transitions: each `Brake` is followed by the `Braking` transition of the same
  reason (at or after the transition number the step was recorded with; a brake may come to
  nothing, when the plan stopped meanwhile, so one without is counted, not a difference), and
  every `Braking` transition of a tracking reason was asked for by a recorded step (or, for a
  file whose first step says a tracking stop still runs, by the step before the file).

A record is JSON only (every value a number, a flag or a string, exact as JSON holds it): it is
read back into the rules' own classes, named in it; a record naming any other is refused.
"""

from __future__ import annotations

import dataclasses
import typing
from typing import Any

from companion import record_format, replay

TOPIC = "/tracking/step"


def _tracking_kinds() -> tuple[type, ...]:
    from companion import tracking_rules as rules

    return (rules.TrackingSample, *typing.get_args(rules.Output))


_typed = replay.RulesReader(_tracking_kinds, "a tracking reading or output")


def step_values(rec: dict[str, Any]) -> tuple[Any, Any, Any, tuple[Any, ...], tuple[float, ...] | None]:
    """(before, reading, after, outputs, window) of a record, typed again from its JSON: the
    rules' own classes only (a record naming another is refused: TypeError, ValueError)."""
    from companion.tracking_rules import StateSeen

    window = rec["window"]
    return (StateSeen(**rec["before"]), _typed(rec["reading"]), StateSeen(**rec["after"]),
            tuple(_typed(o) for o in rec["outputs"]), None if window is None else tuple(window))


@dataclasses.dataclass
class TrackingSteps(replay.Chain):
    """What replaying a file's tracking steps found (replay.Chain), the brakes they asked for,
    how many of those a Braking transition followed, and whether that was checked."""

    brakes: int = 0
    tied: int = 0
    against_transitions: bool = False


@dataclasses.dataclass(frozen=True)
class _Brake:
    seq: int
    transition: int
    reason: str | None  # None: one asked for before the file (its reason unknown, a tracking one)


class _Replayer:
    """Runs the records in `seq` order, carrying the window of errors the records hold by digest."""

    def __init__(self, rules: Any) -> None:
        self.rules = rules
        self.window: tuple[float, ...] | None = ()  # before the next record; None: not known
        self.last: int | None = None  # the seq of the record run last
        self.brakes: list[_Brake] = []

    def check(self, rec: dict[str, Any], previous: tuple[int, Any] | None) -> tuple[Any, list[str]]:
        from companion.tracking_rules import Brake, StateSeen, TrackingState, tracking_step

        seq = int(rec["seq"])
        before, reading, after, outputs, window = step_values(rec)
        label = f"seq {seq} {reading!r}"
        why = replay.chained(label, before, previous, "the rules' state was replaced outside them")
        self.brakes.extend(_Brake(seq, int(rec["transition"]), o.reason) for o in outputs if isinstance(o, Brake))
        if window is not None:
            self.window = tuple(window)
        elif before.errors == 0:
            self.window = ()
        elif self.last != seq - 1:  # the first record read, or after a gap
            self.window = None
        self.last = seq
        if self.window is None:
            return after, [*why, f"{label}: not checkable: the errors before it are unknown (after a gap, until "
                                 "their window empties or the recorder writes it again)"]
        state = TrackingState(before.over, before.said, before.nearing_said, self.window)
        if record_format.fingerprint(StateSeen.of(state)) != record_format.fingerprint(before):
            why.append(f"{label}: " + record_format.first_difference(
                before, StateSeen.of(state), "before", ("recorded", "the records before make")))
        try:
            new, outs = tracking_step(self.rules, state, reading)
        except Exception as exc:  # the recorded call returned: raising now is a difference
            self.window = None
            return after, [*why, f"{label}: replayed raised {type(exc).__name__}: {exc}"]
        self.window = new.errors
        return after, why + replay.compared(label, ("after", after, StateSeen.of(new)),
                                            ("outputs", tuple(outputs), tuple(outs)))


def _brakes_against(out: TrackingSteps, earlier: list[_Brake], brakes: list[_Brake], first: int,
                    transitions: dict[int, tuple[Any, Any, Any]]) -> None:
    """Each brake (those `earlier` than the range first, not counted) tied to the first
    unclaimed Braking transition of its reason at or after the step's number; every Braking
    transition of a tracking reason from `first` on claimed."""
    from companion.supervisor import Braking
    from companion.tracking_rules import BRAKE_REASON

    braking = sorted(s for s, (_b, event, _a) in transitions.items() if isinstance(event, Braking))
    claimed: set[int] = set()
    for brake in [*earlier, *brakes]:
        found = next((s for s in braking if s >= brake.transition and s not in claimed
                      and (transitions[s][1].reason == brake.reason if brake.reason is not None
                           else transitions[s][1].reason.startswith(BRAKE_REASON))), None)
        if found is not None:
            claimed.add(found)
            out.tied += brake in brakes
    for s in braking:
        event = transitions[s][1]
        if s >= first and s not in claimed and event.reason.startswith(BRAKE_REASON):
            out.differences.append(f"transition {s} {event!r} was asked for by no recorded tracking step")


def replay_steps(recs: list[dict[str, Any]], rules: Any, dropped: int = 0,
                 transitions: list[dict[str, Any]] | None = None, inside: set[int] | None = None) -> TrackingSteps:
    """Every record (in `seq` order) run again with `rules` (companion.tracking_rules.TrackingRules)
    and chained to the one before it; with the file's transition records, each brake found.
    `inside`: the seqs in a time range; the records before them are run only to rebuild the
    window of errors."""
    run = _Replayer(rules)
    body = recs if inside is None else [r for r in recs if int(r["seq"]) in inside]
    earlier: list[_Brake] = []  # asked for before the range: their Braking transitions may be in it
    if recs and step_values(recs[0])[1].stop_running:
        # a file's first step while the stop a step asked for is still being planned: that step
        # is in the part before (the file rotated between it and its Braking transition)
        earlier.append(_Brake(int(recs[0]["seq"]) - 1, int(recs[0]["transition"]), None))
    if body and body[0] is not recs[0]:
        replay.replay_chain(TrackingSteps(), recs[:recs.index(body[0])], run.check, 0, "tracking step")
        earlier, run.brakes = earlier + run.brakes, []
    out = TrackingSteps()
    replay.replay_chain(out, body, run.check, dropped, "tracking step")
    out.brakes = len(run.brakes)
    if transitions and body:
        out.against_transitions = True
        _brakes_against(out, earlier, run.brakes, int(body[0]["transition"]), replay.transitions_by_seq(transitions))
    return out


def replay_file(path: str, transitions: list[dict[str, Any]], since: float | None = None,
                until: float | None = None) -> tuple[TrackingSteps, bool]:
    """Replay the file's tracking steps (in the time range), against its `transitions` (the
    records in the same range); and whether it holds any (a record, or a drop counted)."""
    from companion.tracking_rules import TrackingRules

    recs, dropped = replay.numbered_records(path, TOPIC, "tracking_step")
    if not recs:
        return replay_steps([], None, dropped, transitions), bool(dropped)
    cfg = replay.required_config(path, "run its tracking steps with")
    inside = None if since is None and until is None else \
        {int(r["seq"]) for r in replay.numbered_records(path, TOPIC, "tracking_step", since, until)[0]}
    return replay_steps(recs, TrackingRules.of(cfg), dropped, transitions, inside), True


def said(steps: TrackingSteps, recorded: bool) -> str:
    """The replay's line for the tracking steps."""
    brakes = f"{steps.brakes} brake{'s' * (steps.brakes != 1)}"
    if steps.brakes and steps.against_transitions:
        brakes += f", {steps.tied} followed by its Braking transition"
    elif steps.brakes:
        brakes += ", not checked against transitions: none recorded"
    return replay.said_of("tracking steps", steps, recorded, brakes)
