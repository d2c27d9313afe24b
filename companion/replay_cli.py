"""`python -m companion replay FILE.mcap`: run every recorded transition, autopilot step, inbound
read, tracking step, swap, split step, plan budget answer, race step, fleet commit step, command
step and plan again and say whether each reproduces (exit 0), where the first differs (exit 1),
or why the file cannot be replayed (exit 2). What each check covers: companion/replay.py,
companion/replay_autopilot.py, companion/replay_tracking.py, companion/replay_swaps.py,
companion/replay_split.py, companion/replay_budget.py, companion/replay_race.py,
companion/replay_commit.py (a vehicle in a fleet) and companion/replay_commands.py.
"""

from __future__ import annotations

import pickle
import sys

from companion import (
    replay_autopilot,
    replay_budget,
    replay_commands,
    replay_commit,
    replay_race,
    replay_split,
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
        stepped, any_steps = replay_autopilot.replay_file(args.file, recs, args.since, args.until)
        print(replay_autopilot.said(stepped, any_steps), flush=True)
        for more in stepped.differences[1:] if args.keep_going else ():
            print(f"  also: {more}")
        heard = replay_autopilot.said_heartbeats(stepped)
        if heard is not None:
            print(heard, flush=True)
        tracked, any_tracking = replay_tracking.replay_file(args.file, recs, args.since, args.until)
        print(replay_tracking.said(tracked, any_tracking), flush=True)
        for more in tracked.differences[1:] if args.keep_going else ():
            print(f"  also: {more}")
        swaps, any_swaps = replay_swaps.replay_file(args.file, args.since, args.until)
        print(replay_swaps.said(swaps, any_swaps), flush=True)
        for more in swaps.differences[1:] if args.keep_going else ():
            print(f"  also: {more}")
        splits, any_splits = replay_split.replay_file(args.file, args.since, args.until)
        print(replay_split.said(splits, any_splits), flush=True)
        for more in splits.differences[1:] if args.keep_going else ():
            print(f"  also: {more}")
        budget, any_budget = replay_budget.replay_file(args.file, args.since, args.until)
        print(replay_budget.said(budget, any_budget), flush=True)
        for more in budget.differences[1:] if args.keep_going else ():
            print(f"  also: {more}")
        races, any_races = replay_race.replay_file(args.file, recs, args.since, args.until)
        print(replay_race.said(races, any_races), flush=True)
        for more in races.differences[1:] if args.keep_going else ():
            print(f"  also: {more}")
        commits, any_commits = replay_commit.replay_file(args.file, args.since, args.until)
        if any_commits:  # a vehicle in a fleet: said only there
            print(replay_commit.said(commits, any_commits), flush=True)
        for more in commits.differences[1:] if args.keep_going else ():
            print(f"  also: {more}")
        clock, any_clock = replay_commit.replay_clock_file(args.file)
        if any_clock:
            print(replay_commit.said_clock(clock, any_clock), flush=True)
        for more in clock.differences[1:] if args.keep_going else ():
            print(f"  also: {more}")
        commanded, any_commands = replay_commands.replay_file(args.file, args.since, args.until)
        print(replay_commands.said(commanded, any_commands), flush=True)
        for more in commanded.differences[1:] if args.keep_going else ():
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
    if (n == 0 and not recs and not dropped and not decoded and not any_steps and not any_tracking and not any_swaps
            and not any_splits and not any_budget and not any_races and not any_commits and not any_clock
            and not any_commands):
        print("replay: no plan, transition, autopilot, tracking, split, budget, race, commit or command step, clock "
              "sample, swap or inbound message in the recording (or in the time range)", file=sys.stderr)
        return 2
    if n == 0:
        print("plans: none recorded")
    else:
        print(f"plans: {n - bad} of {n} reproduced bit-identically" if bad == 0 or args.keep_going
              else f"plans: plan {n} is the first that differs")
    clean = not (checked.differences or stepped.differences or tracked.differences or decode_bad
                 or swaps.differences or splits.differences or budget.differences or races.differences
                 or commits.differences or clock.differences or commanded.differences)
    return 0 if bad == 0 and clean else 1
