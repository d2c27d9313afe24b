"""Replay of the fleet's commit protocol: every /fleet/commit record run through
`companion.commit.step` again.

In a fleet ([fleet] separation), a new plan is flown only once committed: proposed on the
vehicle's trajectory key, kept for twice the fleet's delay bound, and given up to a conflicting
trajectory that is committed or outranks it (companion/commit.py, docs/fleet.md). Each record
holds one call of the protocol's rule, `step(state, event) -> (state, actions)`: the state
before (our rank, the wait, the phase, the candidate's number and deadline), the event (`Ready`:
a candidate planned, with what was known of the others then, each as its rank, whether it is
committed and whether it conflicts; `Heard`: another vehicle's trajectory; `Tick`; `Cancel`),
the state after and the actions (`Propose`, `Commit`, `Lose`, `Replan`, with the winner and the
reason). Replay runs `step(before, event)` again, compares the state after and the actions
exactly, and checks:
- the chain: one protocol state a run, so each record starts where the one before it ended, and
  the run's first (seq 1) from an idle state;
- the numbering and the drops the recorder counted (`commit_step`; these share the transitions'
  queue), as for transitions.

Whether two trajectories conflict (fail to certify the separation) is decided outside the rule,
by certifying in the fleet frame (companion.traffic), and recorded as the flags it gave; the
certificates themselves travel in the trajectory messages (`/in/...`, `/out/trajectory`).

Each /fleet/clock record holds one sample of the fleet's clock check (companion/clocks.py):
another vehicle's trajectory put, its send time on its clock and its arrival on ours, and the
verdict on our clock after it (why it is off, or null). Replay feeds the samples in order into a
fresh check, with the recorded configuration's `clock_tolerance` and `max_delay`, and compares
each verdict: so why the companion stopped a mission for its clock, and when it trusted it again,
is answered from the file.

A record is JSON only (every value a number, a flag or a string, exact as JSON holds it): it is
read back into the protocol's own classes, named in it; a record naming any other is refused.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from companion import replay

TOPIC = "/fleet/commit"


def _rank(d: dict[str, Any]) -> Any:
    from companion.commit import Rank

    return Rank(int(d["priority"]), str(d["vehicle"]))


def _other(d: dict[str, Any]) -> Any:
    from companion.commit import Other

    return Other(_rank(d["rank"]), bool(d["committed"]), bool(d["conflicts"]), bool(d["conflicts_committed"]))


def _state(d: dict[str, Any]) -> Any:
    from companion.commit import Phase, State

    return State(_rank(d["me"]), float(d["wait"]), Phase(d["phase"]), int(d["seq"]), float(d["deadline"]))


def _event(tagged: dict[str, Any]) -> Any:
    from companion.commit import Cancel, Heard, Ready, Tick

    kind, f = tagged["type"], tagged["fields"]
    if kind == "Ready":
        return Ready(int(f["seq"]), float(f["now"]), tuple(_other(o) for o in f["known"]))
    if kind == "Heard":
        return Heard(float(f["now"]), _other(f["other"]))
    if kind == "Tick":
        return Tick(float(f["now"]))
    if kind == "Cancel":
        return Cancel()
    raise ValueError(f"{kind!r} is not an event of the commit protocol")


def _action(tagged: dict[str, Any]) -> Any:
    from companion.commit import Commit, Lose, Propose, Replan

    kinds: dict[str, type] = {k.__name__: k for k in (Propose, Commit, Lose, Replan)}
    kind = kinds.get(tagged["type"])
    if kind is None:
        raise ValueError(f"{tagged['type']!r} is not an action of the commit protocol")
    return kind(**tagged["fields"])


def step_values(rec: dict[str, Any]) -> tuple[Any, Any, Any, tuple[Any, ...]]:
    """(before, event, after, actions) of a record, typed again from its JSON: the protocol's
    own classes only (a record naming another is refused: ValueError, KeyError, TypeError)."""
    return (_state(rec["before"]), _event(rec["event"]), _state(rec["after"]),
            tuple(_action(a) for a in rec["actions"]))


@dataclasses.dataclass
class CommitSteps(replay.Chain):
    """What replaying a file's commit records found (replay.Chain), and the candidates they
    committed and lost."""

    committed: int = 0
    lost: int = 0


def replay_steps(recs: list[dict[str, Any]], dropped: int = 0) -> CommitSteps:
    """Every record (in `seq` order) run again and chained to the one before it."""
    from companion.commit import Commit, Lose, State, step

    out = CommitSteps()

    def check(rec: dict[str, Any], previous: tuple[int, Any] | None) -> tuple[Any, list[str]]:
        seq = int(rec["seq"])
        before, event, after, actions = step_values(rec)
        label = f"seq {seq} {type(event).__name__}"
        why = replay.chained(label, before, previous, "the protocol's state was replaced outside its rule")
        if seq == 1:
            why += replay.compared(label, ("before (idle, as a service starts)", State(before.me, before.wait), before))
        try:
            new, acts = step(before, event)
        except Exception as exc:  # the recorded call returned: raising now is a difference
            return after, [*why, f"{label}: replayed raised {type(exc).__name__}: {exc}"]
        why += replay.compared(label, ("after", after, new), ("actions", actions, tuple(acts)))
        if not why:
            out.committed += sum(isinstance(a, Commit) for a in actions)
            out.lost += sum(isinstance(a, Lose) for a in actions)
        return after, why

    replay.replay_chain(out, recs, check, dropped, "commit step")
    return out


def replay_file(path: str, since: float | None = None, until: float | None = None) -> tuple[CommitSteps, bool]:
    """Replay the file's commit records (in the time range); and whether it holds any (a
    record, or a drop counted)."""
    recs, dropped = replay.numbered_records(path, TOPIC, "commit_step", since, until)
    return replay_steps(recs, dropped), bool(recs) or bool(dropped)


def said(steps: CommitSteps, recorded: bool) -> str:
    """The replay's line for the commit records."""
    return replay.said_of("fleet commits", steps, recorded, f"{steps.committed} committed, {steps.lost} lost")


# -- the clock check -----------------------------------------------------------------------------

CLOCK_TOPIC = "/fleet/clock"


@dataclasses.dataclass
class ClockSamples(replay.Chain):
    """What replaying a file's clock samples found (replay.Chain), and the verdicts that found
    our clock off (a change from agreeing)."""

    found_off: int = 0


def replay_clock(recs: list[dict[str, Any]], tolerance: float, max_delay: float, dropped: int = 0) -> ClockSamples:
    """Every sample (in `seq` order) into a fresh companion.clocks.ClockCheck, the verdict on our
    clock after each compared with the one recorded. The check keeps WINDOW s of samples: after a
    gap (a record missing) the verdicts are compared still, and a difference there may be the gap's."""
    from companion.clocks import ClockCheck

    out = ClockSamples()
    check_ = ClockCheck(tolerance, max_delay)
    was: list[str | None] = [None]

    def check(rec: dict[str, Any], _previous: tuple[int, Any] | None) -> tuple[Any, list[str]]:
        seq, vehicle = int(rec["seq"]), str(rec["vehicle"])
        sent, arrived = float(rec["sent"]), float(rec["arrived"])
        check_.heard(vehicle, sent, arrived)
        why = check_.ours_off(arrived)
        recorded = rec["off"]
        if recorded is not None and not isinstance(recorded, str):
            raise ValueError(f"seq {seq}: 'off' is neither text nor null")
        out.found_off += why is not None and was[0] is None and why == recorded
        was[0] = why
        label = f"seq {seq} ({vehicle}, sent {sent!r}, arrived {arrived!r})"
        return None, replay.compared(label, ("verdict on our clock", recorded, why))

    replay.replay_chain(out, recs, check, dropped, "clock sample")
    return out


def replay_clock_file(path: str) -> tuple[ClockSamples, bool]:
    """Replay the file's clock samples (all of them: a verdict depends on the window before it);
    and whether it holds any."""
    recs, dropped = replay.numbered_records(path, CLOCK_TOPIC, "clock_sample")
    if not recs:
        return ClockSamples(), bool(dropped)
    cfg = replay.required_config(path, "check its fleet clock with")
    return replay_clock(recs, float(cfg.fleet.clock_tolerance), float(cfg.fleet.max_delay), dropped), True


def said_clock(samples: ClockSamples, recorded: bool) -> str:
    """The replay's line for the clock samples."""
    n = samples.found_off
    return replay.said_of("fleet clock", samples, recorded, f"our clock found off {n} time{'s' * (n != 1)}",
                          alike="judged alike")
