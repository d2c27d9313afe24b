"""Replay of the pop-up obstacles' decisions and their races: every /brakes/race record run
through `companion.race_rules.race_step` again, and each brake found among the transitions.

Each record holds one call of the rules for one pop-up (companion/replans.py `Replans.avoid`,
companion/braking.py `StopGuard.bring_forward` and `Brakes.race`): the pop-up's number and the
step's within it, its rules (its obstacles' ids, the split a replan needs, the time to spare,
how early the stop is prepared), the state before (what it waits for, the braking deadline and
the hit, the notes of deadlines brought forward), the observation (at the pop-up: where the
flown plan hits and the time committed; a deadline brought forward; a turn of the race: control,
the stop asked for, planning or ready and its start, the time committed; the replan's outcome;
its notes when cancelled at the deadline; whether the prepared stop was swapped in), the state
after and the action. Replay runs `race_step(rules, before, observation)` again, compares the
state after and the action exactly (the reasons' texts among them), and checks:
- the chain, per pop-up: its first step starts from the rules' first state, each later one
  from the state the step before it ended in, under the same rules;
- the numbering and the drops the recorder counted (`race_step`; these share the transitions'
  queue), as for transitions;
- with the file's transitions: each brake (`Brake`, `Braked`) is followed by the `Braking`
  transition of the same reason, at or after the transition number the step was recorded with
  (a brake may come to nothing, when the plan stopped meanwhile: counted, not a difference),
  and every `Braking` transition of an obstacle's reason was asked for by a recorded step.

What it does not cover: where the flown plan hits the obstacles and the deadline's estimate
(planner_core.first_hit, braking.brake_deadline: numbers observed), the stop's planning
(braking.plan_stop, a plan record when planned) and how Brakes.brake then stops.

A record is JSON only (every value a number, a flag or a string, exact as JSON holds it): it is
read back into the rules' own classes, named in it; a record naming any other is refused.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from companion import replay

TOPIC = "/brakes/race"
OBSTACLE_REASON = "obstacle"  # the reasons the pop-ups brake for start so ("obstacle ['a']", "obstacles ['a']")


_typed = replay.RulesReader(replay.observations_and_actions("companion.race_rules"), "a race observation or action",
                             ("notes",))


def step_values(rec: dict[str, Any]) -> tuple[Any, Any, Any, Any, Any]:
    """(rules, before, observation, after, action) of a record, typed again from its JSON: the
    rules' own classes only (a record naming another is refused: TypeError, ValueError)."""
    from companion.race_rules import RaceRules, RaceState

    def state(d: dict[str, Any]) -> RaceState:
        return RaceState(**{**d, "notes": tuple(d["notes"])})

    return replay.rule_values(rec, RaceRules, state, _typed)


@dataclasses.dataclass
class Races(replay.Chain):
    """What replaying a file's race steps found (replay.Chain): the pop-ups, the races among
    them, the brakes asked for and how many a Braking transition followed (and whether that
    was checked)."""

    popups: int = 0
    races: int = 0
    brakes: int = 0
    tied: int = 0
    against_transitions: bool = False


@dataclasses.dataclass(frozen=True)
class _Brake:
    seq: int
    transition: int
    reason: str


def _first_state(_rules: Any) -> Any:
    """The state a run starts with."""
    from companion.race_rules import first_state

    return first_state()


class _Replayer:
    """Runs the records in `seq` order, chaining each pop-up's steps."""

    def __init__(self, out: Races) -> None:
        self.out = out
        self.races = replay.RunChains(_first_state, "the race's state was replaced outside its rules")
        self.brakes: list[_Brake] = []

    def check(self, rec: dict[str, Any], _previous: tuple[int, Any] | None) -> tuple[Any, list[str]]:
        from companion.race_rules import Brake, Braked, PopUp, Race, race_step

        seq, race, step = int(rec["seq"]), int(rec["call"]), int(rec["step"])
        rules, before, seen, after, action = step_values(rec)
        label = f"seq {seq} ({rules.what}, race {race} step {step}) {seen!r}"
        why, _ = self.races.chain(label, race, step, seq, rules, before, after, action)
        if isinstance(action, Brake | Braked):
            self.brakes.append(_Brake(seq, int(rec["transition"]), action.reason))
        try:
            new, act = race_step(rules, before, seen)
        except Exception as exc:  # the recorded call returned: raising now is a difference
            return after, [*why, f"{label}: replayed raised {type(exc).__name__}: {exc}"]
        why += replay.compared(label, ("after", after, new), ("action", action, act))
        if not why:
            self.out.popups += isinstance(seen, PopUp)
            self.out.races += isinstance(action, Race)
        return after, why


def _brakes_against(out: Races, brakes: list[_Brake], first: int | None,
                    transitions: dict[int, tuple[Any, Any, Any]]) -> None:
    """Each brake tied to the first unclaimed Braking transition of its reason at or after the
    step's number; every Braking transition of an obstacle's reason from `first` on claimed
    (None: none need be)."""
    from companion.supervisor import Braking

    braking = sorted(s for s, (_b, event, _a) in transitions.items() if isinstance(event, Braking))
    claimed: set[int] = set()
    for brake in brakes:
        found = next((s for s in braking if s >= brake.transition and s not in claimed
                      and transitions[s][1].reason == brake.reason), None)
        if found is not None:
            claimed.add(found)
            out.tied += 1
    for s in braking:
        event = transitions[s][1]
        if first is not None and s >= first and s not in claimed and event.reason.startswith(OBSTACLE_REASON):
            out.differences.append(f"transition {s} {event!r} was asked for by no recorded race step")


def replay_steps(recs: list[dict[str, Any]], dropped: int = 0,
                 transitions: list[dict[str, Any]] | None = None) -> Races:
    """Every record (in `seq` order) run again and chained to the step before it in its
    pop-up; with the file's transition records (None: not checked), each brake found."""
    out = Races()
    run = _Replayer(out)
    replay.replay_chain(out, recs, run.check, dropped, "race step")
    out.brakes = len(run.brakes)
    if transitions and recs:
        out.against_transitions = True
        _brakes_against(out, run.brakes, _first_claimable(recs), replay.transitions_by_seq(transitions))
    return out


def _first_claimable(recs: list[dict[str, Any]]) -> int | None:
    """The first transition number from which every Braking transition of an obstacle's reason
    must have been asked for by a record here. A pop-up is decided under the navigator's lock,
    which its race holds until its brake's Braking transition: only the braking race's own
    deadline steps (`Forward`, outside the lock) come between a brake and its transition. So in
    records that begin mid-race (a file part after a rotation, a time range), a Braking
    transition before the first pop-up that starts here may be a brake asked for before them."""
    if int(recs[0]["step"]) == 1:
        return int(recs[0]["transition"])
    return next((int(r["transition"]) for r in recs if int(r["step"]) == 1), None)


def replay_file(path: str, transitions: list[dict[str, Any]], since: float | None = None,
                until: float | None = None) -> tuple[Races, bool]:
    """Replay the file's race steps (in the time range), against its `transitions` (the records
    in the same range); and whether it holds any (a record, or a drop counted)."""
    recs, dropped = replay.numbered_records(path, TOPIC, "race_step", since, until)
    return replay_steps(recs, dropped, transitions), bool(recs) or bool(dropped)


def said(races: Races, recorded: bool) -> str:
    """The replay's line for the race steps."""
    brakes = f"{races.brakes} brake{'s' * (races.brakes != 1)}"
    if races.brakes and races.against_transitions:
        brakes += f", {races.tied} followed by its Braking transition"
    elif races.brakes:
        brakes += ", not checked against transitions: none recorded"
    detail = f"{races.popups} pop-up{'s' * (races.popups != 1)}, {races.races} raced, {brakes}"
    return replay.said_of("races", races, recorded, detail)
