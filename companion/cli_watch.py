"""`python -m companion watch`: print a vehicle's status and events (telemetry too), from the
addressed companion only; `--wait-for` a state, home, or the link."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from typing import Any

from companion.cli_client import EXIT_UNFINISHED, Origin, client_session


def status_reached(status: dict[str, Any], wanted: str) -> bool:
    """`--wait-for`: a state name (IDLE, READY, HOLDING, ...), or `link` (the autopilot is heard),
    or `home` (it reported a valid home: PX4 does once its estimator is ready, ArduPilot once its
    EKF origin is set; before, missions are refused as "not ready"), or `ready` (home and a
    position estimate: real ArduCopter reports home ~22 s before its first LOCAL_POSITION_NED,
    and `start` is refused without one)."""
    if wanted == "link":
        return status.get("link") is True
    if wanted == "home":
        return isinstance(status.get("home"), list)
    if wanted == "ready":
        return isinstance(status.get("home"), list) and status.get("position_ok") is True
    return bool(status.get("state") == wanted)


def cmd_watch(args: argparse.Namespace) -> int:
    session = client_session(args, args.duration or 30.0)
    topics = ["status", "events"] + (["telemetry"] if args.telemetry else [])
    last_heard = [time.monotonic()]
    reached = [False]

    def show(sample: Any) -> None:
        key = str(sample.key_expr).rsplit("/", 1)[-1]
        text = sample.payload.to_bytes().decode("utf-8", "replace")
        body: Any = None
        if key != "telemetry":  # telemetry is small and frequent: it carries no session id
            with contextlib.suppress(ValueError):
                body = json.loads(text)
            if not origin.accepts(key, sample, body):
                return
        elif str(sample.key_expr) != f"{base}/telemetry":
            return
        last_heard[0] = time.monotonic()
        print(f"{key} {text}", flush=True)
        if args.wait_for and key == "status":
            with contextlib.suppress(ValueError, AttributeError):
                if status_reached(json.loads(text), args.wait_for):
                    reached[0] = True

    base = f"{args.prefix}/{args.vehicle}"
    origin = Origin(session, base)
    print(f"watch: {origin.note}", file=sys.stderr, flush=True)
    subs = [session.declare_subscriber(f"{base}/{t}", show) for t in topics]
    deadline = time.monotonic() + args.duration if args.duration else None
    said = 0.0
    try:
        while (deadline is None or time.monotonic() < deadline) and not reached[0]:
            time.sleep(0.1)
            quiet = time.monotonic() - last_heard[0]
            if quiet >= args.silence and time.monotonic() - said >= args.silence:
                said = time.monotonic()
                print(f"watch: nothing heard from vehicle {args.vehicle!r} for {quiet:.0f} s "
                      "(is the companion running? --vehicle, --prefix and --connect must match it)",
                      file=sys.stderr, flush=True)
    except KeyboardInterrupt:
        pass
    finally:
        for s in subs:
            s.undeclare()
        session.close()
    if origin.summary():
        print(f"watch: {origin.summary()}", file=sys.stderr)
    if args.wait_for and not reached[0]:
        return EXIT_UNFINISHED
    return 0
