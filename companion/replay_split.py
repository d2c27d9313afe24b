"""Replay of the split-and-swap loop's decisions: every /navigator/split record run through
`companion.split_rules.split_step` again.

Each record holds one call of the rules made by `SplitSwap.at_split` (companion/split_swap.py)
for one plan made in flight: the call's number and the step's within it, what asked, the call's
rules (the lead asked for, the fleet and its wait, when an obstacle would be hit), the state
before, the observation (the time committed, the plan's outcome and how long it took, the fleet's
answer, the swap's refusal, whether the flown plan holds still), the state after and the action.
Replay runs `split_step(rules, before, observation)` again, compares the state after (the lead
of the next split, the causes counted, the reason, the texts said in order) and the action
exactly, and checks:
- the chain, per call: its first step starts from the rules' first state, each later one from
  the state the step before it ended in, under the same rules;
- the numbering and the drops the recorder counted (`split_step`; these share the transitions'
  queue), as for transitions;
- with the file's /control/swap records: each swap the loop observed is the swap record of the
  number the step names (`swap`), of the same `what`, split and refusal.

A record is JSON only (every value a number, a flag or a string, exact as JSON holds it): it is
read back into the rules' own classes, named in it; a record naming any other is refused.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from companion import replay

TOPIC = "/navigator/split"


_typed = replay.RulesReader(replay.observations_and_actions("companion.split_rules"), "a split observation or action")


def step_values(rec: dict[str, Any]) -> tuple[Any, Any, Any, Any, Any]:
    """(rules, before, observation, after, action) of a record, typed again from its JSON: the
    rules' own classes only (a record naming another is refused: TypeError, ValueError)."""
    from companion.split_rules import SplitRules, SplitState

    def state(d: dict[str, Any]) -> SplitState:
        return SplitState(**{**d, "said": tuple(d["said"])})

    return replay.rule_values(rec, SplitRules, state, _typed)


@dataclasses.dataclass
class Splits(replay.Chain):
    """What replaying a file's split steps found (replay.Chain), how many calls ended with a
    plan swapped in and how many gave up (or were refused), and the swaps checked against
    their /control/swap records."""

    swapped: int = 0
    given_up: int = 0
    swaps_checked: int = 0


def _first_state(rules: Any) -> Any:
    """The state a run starts with."""
    from companion.split_rules import first_state

    return first_state(rules)


class _Replayer:
    """Runs the records in `seq` order, chaining each call's steps."""

    def __init__(self, out: Splits, swaps: dict[int, dict[str, Any]] | None) -> None:
        self.out = out
        self.swaps = swaps  # the file's /control/swap records by seq (None: not checked)
        self.calls = replay.RunChains(_first_state, "the loop's state was replaced outside its rules")

    def check(self, rec: dict[str, Any], _previous: tuple[int, Any] | None) -> tuple[Any, list[str]]:
        from companion.split_rules import (
            Done,
            GiveUp,
            Moved,
            Refused,
            SwapDecided,
            split_step,
        )

        seq, call, step = int(rec["seq"]), int(rec["call"]), int(rec["step"])
        rules, before, seen, after, action = step_values(rec)
        label = f"seq {seq} ({rec['what']}, call {call} step {step}) {seen!r}"
        why, _ = self.calls.chain(label, call, step, seq, rules, before, after, action)
        try:
            new, act = split_step(rules, before, seen)
        except Exception as exc:  # the recorded call returned: raising now is a difference
            return after, [*why, f"{label}: replayed raised {type(exc).__name__}: {exc}"]
        why += replay.compared(label, ("after", after, new), ("action", action, act))
        if isinstance(seen, SwapDecided | Moved):
            t_split = before.t_split if isinstance(seen, SwapDecided) else before.t_later
            why += self._swap(label, int(rec["swap"]), rec["what"], t_split, seen.refusal)
        if not why:
            self.out.swapped += isinstance(action, Done)
            self.out.given_up += isinstance(action, GiveUp | Refused)
        return after, why

    def _swap(self, label: str, number: int, what: str, t_split: float, refusal: str) -> list[str]:
        """The swap observed is the /control/swap record `number`, decided alike."""
        if self.swaps is None:
            return []
        swap = self.swaps.get(number)
        if swap is None:
            return [f"{label}: names swap {number}, which the file does not hold"]
        self.out.swaps_checked += 1
        if (swap["what"], float(swap["t_split"]), swap["refusal"]) != (what, t_split, refusal):
            return [f"{label}: swap {number} is ({swap['what']!r}, split {float(swap['t_split'])!r}, refusal "
                    f"{swap['refusal']!r}), the step observed ({what!r}, split {t_split!r}, refusal {refusal!r})"]
        return []


def replay_steps(recs: list[dict[str, Any]], dropped: int = 0,
                 swaps: list[dict[str, Any]] | None = None) -> Splits:
    """Every record (in `seq` order) run again and chained to the step before it in its call;
    with the file's swap records (None: not checked), each swap observed found."""
    out = Splits()
    run = _Replayer(out, None if swaps is None else {int(s["seq"]): s for s in swaps})
    replay.replay_chain(out, recs, run.check, dropped, "split step")
    return out


def replay_file(path: str, since: float | None = None, until: float | None = None) -> tuple[Splits, bool]:
    """Replay the file's split steps (in the time range), against its swap records (all of
    them: a swap is decided just before the step that observed it, maybe outside the range);
    and whether it holds any (a record, or a drop counted)."""
    recs, dropped = replay.numbered_records(path, TOPIC, "split_step", since, until)
    swaps, _ = replay.numbered_records(path, "/control/swap", "swap") if recs else ([], 0)
    return replay_steps(recs, dropped, swaps or None), bool(recs) or bool(dropped)


def said(splits: Splits, recorded: bool) -> str:
    """The replay's line for the split steps."""
    return replay.said_of("splits", splits, recorded, f"{splits.swapped} swapped in, {splits.given_up} given up")
