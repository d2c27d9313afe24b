"""Replay of the autopilot watch's rules: every /autopilot/step record run through
`companion.autopilot_rules.watch_step` again, and its events found in the supervisor's
transitions.

Each record holds one call: the watch's state before, the flight state the rules read, the
reading (a heartbeat, a position, the landed state, a note, a link check), the time, the state
after and the outputs. Replay runs `watch_step(rules, before, flight, reading, now)` again, the
rules (the autopilot's ids, the link timeout) from the configuration the recording service ran
with, and compares the state after and the outputs exactly, and checks:
- the chain: each record starts from the watch state the one before it ended in, and the
  numbers have no gap (nor did the recorder count a drop);
- the readable fields are what the pickle holds;
- with the transitions of the same file, end to end: the step's supervisor events are the
  events of the transitions it is numbered with (`transition`: the first, then in order), the
  first of them starting from the flight state the step read; the flight state each step read
  is the one the transition before it left; and every transition of an event only the watch
  makes (Heartbeat, Disarmed, ModeReport, GroundLearnt, HeightReport, LandedStateReport,
  LinkLost) was made by a recorded step. From MAVLink reading to flight state, the chain is then
  checked whole.

Step records are unpickled with an allow-list of their own: the watch's state, readings and
outputs, the flight state and its enum, the supervisor events the watch makes.
"""

from __future__ import annotations

import dataclasses
import functools
import json
import typing
from typing import Any

from companion import record_format, replay

TOPIC = "/autopilot/step"


@functools.cache
def _step_types() -> frozenset[tuple[str, str]]:
    from companion import autopilot_rules as rules
    from companion.flight import FlightState, State

    kinds = (rules.WatchState, rules.WatchRules, FlightState, State, *typing.get_args(rules.Reading), *typing.get_args(rules.Output))
    return frozenset((k.__module__, k.__qualname__) for k in kinds)


def loads_step(text: str) -> Any:
    return replay.loads_narrow(text, _step_types(), "an autopilot step record")


def step_records(path: str, since: float | None = None,
                 until: float | None = None) -> tuple[list[dict[str, Any]], int]:
    """The /autopilot/step records of a file and the step records dropped (replay.numbered_records)."""
    return replay.numbered_records(path, TOPIC, "autopilot_step", since, until)


@dataclasses.dataclass
class Steps(replay.Chain):
    """What replaying a file's autopilot steps found (replay.Chain), and the supervisor events
    they made and whether those were checked against the transitions."""

    events: int = 0
    heartbeats: int = 0  # heartbeat readings recorded with the fields they were read from
    heartbeats_alike: int = 0  # ... that read the same again (companion.wire.vehicle.read_heartbeat)
    against_transitions: bool = False


@dataclasses.dataclass(frozen=True)
class _Step:
    seq: int
    transition: int
    flight: Any
    events: tuple[Any, ...]
    wire: bool = False  # a heartbeat recorded with the fields it was read from


def check_step(rec: dict[str, Any], previous: tuple[int, Any] | None,
               rules: Any) -> tuple[Any, _Step | None, list[str]]:
    """One record run through `watch_step` again: (its recorded watch state after, for the next
    record's chain check; what it read and made, for the end-to-end check; what differs)."""
    from companion import channels as ch
    from companion.autopilot_rules import WATCH_EVENTS, watch_step

    seq = int(rec["seq"])
    if rec.get("pickle") is None:
        return None, None, [f"seq {seq} {rec['reading'].get('type')}: the values were not recorded (not picklable)"]
    before, flight, reading, now, after, outputs = loads_step(rec["pickle"])
    label, why = f"seq {seq} {reading!r}", []
    readable = json.loads(ch.dumps(ch.step_fields(before, flight, reading, now, after, outputs)))
    for name, value in readable.items():
        if rec.get(name) != value:
            why.append(f"{label}: the record's {name} (JSON) is not its pickled value")
    why += replay.chained(label, before, previous, "the watch's state was replaced outside its rules")
    made = _Step(seq, int(rec["transition"]), flight, tuple(o for o in outputs if isinstance(o, WATCH_EVENTS)),
                 getattr(reading, "wire", None) is not None)
    why.extend(_read_again(label, reading))
    try:
        new, outs = watch_step(rules, before, flight, reading, now)
    except Exception as exc:  # the recorded call returned: raising now is a difference
        why.append(f"{label}: replayed raised {type(exc).__name__}: {exc}")
        return after, made, why
    return after, made, why + replay.compared(label, ("after", after, new), ("outputs", tuple(outputs), tuple(outs)))


def _read_again(label: str, reading: Any) -> list[str]:
    """A heartbeat's reading against its fields as received, read again as the link reads them
    (the mode's name from PX4's or ArduPilot's custom mode, armed from base_mode)."""
    from companion.autopilot_rules import HeartbeatSeen
    from companion.wire.vehicle import read_heartbeat

    if not isinstance(reading, HeartbeatSeen) or reading.wire is None:
        return []
    again = read_heartbeat(reading.autopilot, *reading.wire)
    if again == (reading.autopilot, reading.mode, reading.armed):
        return []
    a, t, b, c = reading.wire
    return [f"{label}: the heartbeat as received (MAV_AUTOPILOT {a}, MAV_TYPE {t}, base_mode {b}, custom_mode {c}) "
            f"reads as {again[0]} {again[1]!r} {'armed' if again[2] else 'disarmed'}, recorded {reading.autopilot} "
            f"{reading.mode!r} {'armed' if reading.armed else 'disarmed'}"]


def _end_to_end(made: list[_Step], transitions: dict[int, tuple[Any, Any, Any]]) -> list[str]:
    """The steps' events against the supervisor's transitions (see the module's docstring)."""
    from companion.autopilot_rules import WATCH_EVENTS

    fp = record_format.fingerprint
    why: list[str] = []
    claimed: set[int] = set()
    for i, step in enumerate(made):
        label = f"seq {step.seq}"
        seen = transitions.get(step.transition - 1)
        if seen is not None and fp(seen[2]) != fp(step.flight):
            where = record_format.first_difference(seen[2], step.flight, "flight",
                                            (f"transition {step.transition - 1} left", "the step read"))
            why.append(f"{label}: read another flight state than the supervisor's ({where})")
        bound = made[i + 1].transition if i + 1 < len(made) else max(transitions, default=0) + 1
        at = step.transition
        for k, event in enumerate(step.events):
            # the first event is handled right after the step; an action of one event may lead
            # to other handle calls before the next
            found = next((s for s in range(at, max(bound, at + 1)) if s in transitions and s not in claimed
                          and fp(transitions[s][1]) == fp(event)), None) if k else \
                (at if at in transitions and fp(transitions[at][1]) == fp(event) else None)
            if found is None:
                if all(s in transitions for s in range(at, max(bound, at + 1))):
                    why.append(f"{label}: its event {event!r} is not transition {at}"
                               + ("" if not k else f" nor one after it before {bound}"))
                break  # a transition record missing: the transitions' own replay names it
            if k == 0 and fp(transitions[found][0]) != fp(step.flight):
                why.append(f"{label}: transition {found} did not start from the flight state the step read")
            claimed.add(found)
            at = found + 1
    if made:
        lo = made[0].transition
        hi = max([*claimed, made[-1].transition - 1])
        for s in sorted(transitions):
            event = transitions[s][1]
            if lo <= s <= hi and s not in claimed and isinstance(event, WATCH_EVENTS):
                why.append(f"transition {s} {event!r} was made by no recorded autopilot step")
    return why


def replay_steps(recs: list[dict[str, Any]], rules: Any, dropped: int = 0,
                 transitions: list[dict[str, Any]] | None = None) -> Steps:
    """Every step record (in `seq` order) run again with `rules` (the recording's configuration's:
    companion.autopilot_rules.WatchRules) and chained to the one before it; with the file's
    transition records, the end-to-end check."""
    made: list[_Step] = []
    out = Steps()

    def check(rec: dict[str, Any], previous: tuple[int, Any] | None) -> tuple[Any, list[str]]:
        after, step, why = check_step(rec, previous, rules)
        if step is not None and step.wire:
            out.heartbeats += 1
            out.heartbeats_alike += not any("the heartbeat as received" in w for w in why)
        if step is not None:
            made.append(step)
        return after, why

    replay.replay_chain(out, recs, check, dropped, "autopilot step")
    out.events = sum(len(step.events) for step in made)
    if transitions:
        out.against_transitions = True
        out.differences.extend(_end_to_end(made, replay.transitions_by_seq(transitions)))
    return out


def replay_file(path: str, transitions: list[dict[str, Any]], since: float | None = None,
                until: float | None = None) -> tuple[Steps, bool]:
    """Replay the file's steps (in the time range), against its `transitions` (the records in
    the same range); and whether it holds any (a record, or a drop counted)."""
    from companion.autopilot_rules import WatchRules

    recs, dropped = step_records(path, since, until)
    if not recs:
        return replay_steps([], None, dropped, transitions), bool(dropped)
    cfg = replay.required_config(path, "run its autopilot steps with")
    return replay_steps(recs, WatchRules.of(cfg), dropped, transitions), True


def said_heartbeats(steps: Steps) -> str | None:
    """The replay's line for the heartbeats read again (None: none recorded with their fields)."""
    if not steps.heartbeats:
        return None
    return (f"heartbeats: {steps.heartbeats_alike} of {steps.heartbeats} read again alike (mode and armed from "
            "each one's fields as received)")


def said(steps: Steps, recorded: bool) -> str:
    """The replay's line for the steps."""
    events = (f"{steps.events} events, each a recorded transition" if steps.against_transitions
              else f"{steps.events} events, not checked against transitions: none recorded")
    return replay.said_of("autopilot steps", steps, recorded, events)
