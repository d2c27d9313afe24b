"""`python -m companion replay FILE.mcap`: run every recorded transition, autopilot step, inbound
read, tracking step, swap, split step, plan budget answer, race step, fleet commit step, command
step, stall step, hand-over hold step, plan choice and plan again and say whether each reproduces (exit 0), where the first differs (exit 1),
or why the file cannot be replayed (exit 2). What each check covers: companion/replay.py,
companion/replay_autopilot.py, companion/replay_tracking.py, companion/replay_swaps.py,
companion/replay_split.py, companion/replay_budget.py, companion/replay_race.py,
companion/replay_commit.py (a vehicle in a fleet), companion/replay_commands.py,
companion/replay_stalls.py, companion/replay_hold.py and companion/replay_choice.py.
"""

from __future__ import annotations

import pickle
import sys
from collections.abc import Callable
from typing import Any

from companion import (
    replay_autopilot,
    replay_budget,
    replay_choice,
    replay_commands,
    replay_commit,
    replay_hold,
    replay_race,
    replay_split,
    replay_stalls,
    replay_swaps,
    replay_tracking,
)
from companion.record_format import environment
from companion.replay import (
    decoded_records,
    plan_records,
    recorded_environment,
    replay_decoded,
    replay_one,
    replay_transitions,
    required_config,
    transition_records,
)

_Check = tuple[Callable[[], tuple[Any, bool]], Callable[[Any, bool], str | None]]


def _checks(file: str, recs: list[Any], since: float | None, until: float | None) -> list[_Check]:
    """Each recorded loop's replay (run: its result and whether the file holds any) and what it
    says, in the order printed; a fleet's commits and clock are said only where there are any."""

    def autopilot(r: Any, any_: bool) -> str:
        heard = replay_autopilot.said_heartbeats(r)
        return replay_autopilot.said(r, any_) + ("" if heard is None else "\n" + heard)

    def fleet_only(said: Callable[[Any, bool], str]) -> Callable[[Any, bool], str | None]:
        return lambda r, any_: said(r, any_) if any_ else None

    return [
        (lambda: replay_autopilot.replay_file(file, recs, since, until), autopilot),
        (lambda: replay_tracking.replay_file(file, recs, since, until), replay_tracking.said),
        (lambda: replay_swaps.replay_file(file, since, until), replay_swaps.said),
        (lambda: replay_split.replay_file(file, since, until), replay_split.said),
        (lambda: replay_budget.replay_file(file, since, until), replay_budget.said),
        (lambda: replay_race.replay_file(file, recs, since, until), replay_race.said),
        (lambda: replay_commit.replay_file(file, since, until), fleet_only(replay_commit.said)),
        (lambda: replay_commit.replay_clock_file(file), fleet_only(replay_commit.said_clock)),
        (lambda: replay_commands.replay_file(file, since, until), replay_commands.said),
        (lambda: replay_stalls.replay_file(file, since, until), replay_stalls.said),
        (lambda: replay_hold.replay_file(file, since, until), replay_hold.said),
        (lambda: replay_choice.replay_file(file, since, until), replay_choice.said),
    ]


def main(argv: list[str]) -> int:
    import argparse

    from mcap.exceptions import McapError

    p = argparse.ArgumentParser(prog="python -m companion replay", description=(__doc__ or "").splitlines()[0])
    p.add_argument("file")
    p.add_argument("--from", dest="since", type=float, default=None, metavar="T",
                   help="seconds from the start of the recording")
    p.add_argument("--until", type=float, default=None, metavar="T")
    p.add_argument("--keep-going", action="store_true",
                   help="replay every plan and list every transition difference, not only the first")
    args = p.parse_args(argv)
    n = bad = 0
    differences: list[str] = []
    found: list[bool] = []
    try:
        here, there = environment(), recorded_environment(args.file)
        differ = {k: (there.get(k), v) for k, v in here.items() if k in there and there[k] != v}
        if differ:
            print("note: recorded on another environment (" + ", ".join(f"{k} {a} here {b}" for k, (a, b)
                  in differ.items()) + "): its numerical kernels may round differently", flush=True)
        recs, dropped = transition_records(args.file, args.since, args.until)
        checked = replay_transitions(recs, dropped)
        if not recs and not dropped:
            print("transitions: none recorded", flush=True)
        elif not checked.differences:
            print(f"transitions: {checked.total} of {checked.total} reproduced", flush=True)
        else:
            print(f"transitions: {checked.reproduced} of {checked.total} reproduced; first difference: "
                  f"{checked.differences[0]}", flush=True)
            for more in checked.differences[1:] if args.keep_going else ():
                print(f"  also: {more}")
        for run, said in _checks(args.file, recs, args.since, args.until):
            result, any_ = run()
            found.append(any_)
            text = said(result, any_)
            if text is not None:
                print(text, flush=True)
            differences.extend(result.differences)
            for more in result.differences[1:] if args.keep_going else ():
                print(f"  also: {more}")
        decoded = decoded_records(args.file, args.since, args.until)
        decode_bad: list[str] = []
        if decoded:
            cfg = required_config(args.file, "read its messages with")
            decode_bad = [why for why in (replay_decoded(rec, cfg) for rec in decoded) if why]  # ms each
            alike = f"messages: {len(decoded) - len(decode_bad)} of {len(decoded)} read again alike"
            print(alike + (f"; first difference: {decode_bad[0]}" if decode_bad else ""), flush=True)
            for more in decode_bad[1:] if args.keep_going else ():
                print(f"  also: {more}")
        else:
            print("messages: none recorded", flush=True)
        for rec in plan_records(args.file, args.since, args.until):
            r = replay_one(rec)
            n += 1
            mark = "identical" if r.identical else "DIFFERS"
            print(f"plan {r.seq:4d} {r.function}: {mark} (recorded {r.recorded_ms:.1f} ms, "
                  f"replayed {r.replayed_ms:.1f} ms)", flush=True)
            if not r.identical:
                bad += 1
                print(f"  first difference: {r.difference}")
                if not args.keep_going:
                    break
    except (OSError, ValueError, KeyError, TypeError, pickle.UnpicklingError, McapError) as exc:
        print(f"replay: {args.file}: {exc}", file=sys.stderr)
        return 2
    if n == 0 and not recs and not dropped and not decoded and not any(found):
        print("replay: no plan, transition, autopilot, tracking, split, budget, race, commit, command, stall or "
              "hold step, plan choice, clock sample, swap or inbound message in the recording (or in the time range)", file=sys.stderr)
        return 2
    if n == 0:
        print("plans: none recorded")
    else:
        print(f"plans: {n - bad} of {n} reproduced bit-identically" if bad == 0 or args.keep_going
              else f"plans: plan {n} is the first that differs")
    clean = not (checked.differences or differences or decode_bad)
    return 0 if bad == 0 and clean else 1
