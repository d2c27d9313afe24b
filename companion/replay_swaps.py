"""Replay of the swap's rule: every /control/swap record decided again by
`companion.control.swap_refusal`.

Each record holds one decision: what asked (a mission's start, a change, a pop-up's replan, a
stop, ...), the trajectory time then, the lead and the rate the setpoints went out at, the
split, the flown trajectory and the new one, and the refusal ("" when the new plan was swapped
in). Replay decides it again from those values and compares the refusal word for word, and
checks the readable fields against the pickle and the numbering (a gap, or a drop the recorder
counted, is a difference: a decision not seen). So when a plan was swapped in, or why it was not
(the split had passed while planning, an internal check), is reproduced from the values the
service decided it with; which plan was asked for, and when, is not (docs/recording.md).

Swap records are unpickled with an allow-list of their own: the trajectory class and numpy's
arrays.
"""

from __future__ import annotations

import dataclasses
import functools
import json
from typing import Any

from companion import replay

TOPIC = "/control/swap"


@functools.cache
def _swap_types() -> frozenset[tuple[str, str]]:
    from planner_core import Trajectory

    plain = {("copyreg", "_reconstructor"), ("copyreg", "__newobj__"), ("builtins", "object")}
    return frozenset({(Trajectory.__module__, Trajectory.__qualname__), *replay.NUMPY_CLASSES, *plain})


def loads_swap(text: str) -> Any:
    return replay.loads_narrow(text, _swap_types(), "a swap record")


@dataclasses.dataclass
class Swaps(replay.Chain):
    """What replaying a file's swap decisions found (replay.Chain: `reproduced` of `total`, the
    differences), and how many of those decided alike swapped a plan in."""

    swapped: int = 0


def decide_again(rec: dict[str, Any]) -> list[str]:
    """One record decided again: what differs (nothing: alike)."""
    from companion import channels as ch
    from companion.control import swap_refusal

    seq = int(rec["seq"])
    label = f"swap {seq} ({rec.get('what', '?')})"
    if rec.get("pickle") is None:
        return [f"{label}: the trajectories were not recorded (not picklable)"]
    old, new = loads_swap(rec["pickle"])
    why: list[str] = []
    readable = json.loads(ch.dumps({"old": ch.traj_span(old), "new": ch.traj_span(new)}))
    if readable["old"] != rec.get("old") or readable["new"] != rec.get("new"):
        why.append(f"{label}: the record's trajectories (JSON) are not its pickled ones")
    try:
        again = swap_refusal(old, new, float(rec["now"]), float(rec["lead"]), float(rec["rate_hz"]),
                             float(rec["t_split"]))
    except Exception as exc:  # the recorded decision was made: raising now is a difference
        return [*why, f"{label}: replayed raised {type(exc).__name__}: {exc}"]
    if again != rec["refusal"]:
        why.append(f"{label} at {float(rec['now']):.3f} s, split {float(rec['t_split']):.3f} s, lead "
                   f"{float(rec['lead']) * 1000:.1f} ms: recorded {_decision(rec['refusal'])}, decided again "
                   f"{_decision(again)}")
    return why


def _decision(refusal: str) -> str:
    return repr(refusal) if refusal else "swapped in"


def replay_swaps(recs: list[dict[str, Any]], dropped: int = 0) -> Swaps:
    """Every swap record (in `seq` order) decided again; gaps in the numbers and the drops the
    recorder counted are differences (replay.replay_chain; no state runs from one to the next)."""
    out = Swaps()

    def check(rec: dict[str, Any], _previous: tuple[int, Any] | None) -> tuple[Any, list[str]]:
        why = decide_again(rec)
        out.swapped += not why and rec["refusal"] == ""
        return None, why

    replay.replay_chain(out, recs, check, dropped, "swap")
    return out


def said(swaps: Swaps, recorded: bool) -> str:
    """The replay's line for the swaps."""
    refused = swaps.total - swaps.swapped
    return replay.said_of("swaps", swaps, recorded, f"{swaps.swapped} swapped in, {refused} refused", "decided alike")


def replay_file(path: str, since: float | None = None, until: float | None = None) -> tuple[Swaps, bool]:
    """Replay the file's swap decisions (in the time range); and whether it holds any (a record,
    or a drop counted)."""
    recs, dropped = replay.numbered_records(path, TOPIC, "swap", since, until)
    return replay_swaps(recs, dropped), bool(recs) or bool(dropped)
