"""`python -m companion send`: put a message on one or more vehicles' exact keys and wait for
each companion's outcome (exit codes: companion.cli_client)."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from pathlib import Path
from typing import Any

from companion.cli_client import (
    EXIT_ACCESS_DENIED,
    EXIT_DENIED,
    EXIT_NO_ANSWER,
    EXIT_OK,
    EXIT_REFUSED,
    EXIT_REJECTED,
    EXIT_UNFINISHED,
    EXIT_USAGE,
    Origin,
    client_session,
)

# How long `send` waits by default: a command runs its whole sequence (takeoff: ~10 s).
DEFAULT_WAIT = {"command": 30.0, "mission": 30.0, "obstacles": 10.0, "change": 10.0}


def outcome(key: str, events: list[dict[str, Any]]) -> int | None:
    """The exit code the events so far decide, None while undecided."""
    mine = [e for e in events if e.get("key") == key]
    for e in mine:
        kind = e.get("type")
        if kind == "rejected":
            return EXIT_REJECTED
        if kind == "refused":
            # `by` says who refused (a companion before `by` existed: its "failed:" prefix)
            by = e.get("by")
            denied = by == "autopilot" if by is not None else "failed:" in str(e.get("reason", ""))
            return EXIT_DENIED if denied else EXIT_REFUSED
        if kind == "accepted" and key != "command":
            return EXIT_OK
        if kind == "completed":
            return EXIT_OK
    return None


def vehicles_of(text: str) -> list[str]:
    """`--vehicle A,B,C`: the vehicles, in order, each once; a bad name raises ValueError."""
    out: list[str] = []
    for v in text.split(","):
        v = v.strip()
        if not v or any(c in v for c in "/*?$#"):
            raise ValueError(f"--vehicle: {v!r} is not a vehicle id (ids are joined with ',', no wildcards: "
                             "a put on a wildcard key is refused by every companion)")
        if v not in out:
            out.append(v)
    return out


class Target:
    """One vehicle a `send` goes to: its subscriptions, the companion found, the outcome."""

    def __init__(self, session: Any, args: argparse.Namespace, vehicle: str) -> None:
        self.vehicle = vehicle
        self.base = f"{args.prefix}/{vehicle}"
        self.events: list[dict[str, Any]] = []
        self.statuses: list[dict[str, Any]] = []
        self.heard = False
        self.shown = 0
        self.code: int | None = None
        self.done = False
        self.origin: Origin | None = None  # set before the message goes out; nothing is taken before
        self.subs = [session.declare_subscriber(f"{self.base}/events", self._taker(self.events, "events")),
                     session.declare_subscriber(f"{self.base}/status", self._taker(self.statuses, "status"))]
        self.pub: Any = None
        self.matched: list[bool] = []

    def _taker(self, into: list[dict[str, Any]], topic: str) -> Any:
        def take(sample: Any) -> None:
            body: Any = None
            with contextlib.suppress(ValueError):
                body = json.loads(sample.payload.to_bytes())
            if self.origin is None or not self.origin.accepts(topic, sample, body) or not isinstance(body, dict):
                return
            self.heard = True
            into.append(body)
        return take

    def show(self, tagged: bool) -> None:
        for e in self.events[self.shown:]:
            print(json.dumps({"vehicle": self.vehicle, **e} if tagged and "vehicle" not in e else e), flush=True)
        self.shown = len(self.events)

    def reached(self, wanted: str | None) -> bool:
        return bool(self.statuses and self.statuses[-1].get("state") == wanted)

    def verdict(self, args: argparse.Namespace, wait: float, say: str) -> int:
        """The exit code for this vehicle, saying on stderr why it is not 0."""
        code, key = self.code, args.key
        if code is None:
            if not self.heard:
                print(f"{say}no companion answered for vehicle {self.vehicle!r} within {wait:g} s "
                      "(is it running? --vehicle, --prefix and --connect must match it)", file=sys.stderr)
                return EXIT_NO_ANSWER
            if not any(self.matched) and not [e for e in self.events if e.get("key") == key]:
                print(f"{say}denied: the companion of vehicle {self.vehicle!r} is heard, but nothing receives "
                      f"{self.base}/{key} from this client: Zenoh's access control denies this user publishing "
                      "there (an observer may only watch; use an operator's credentials)", file=sys.stderr)
                return EXIT_ACCESS_DENIED
            print(f"{say}the companion did not say within {wait:g} s whether {key} was done", file=sys.stderr)
            return EXIT_UNFINISHED
        if code == EXIT_OK and args.wait_for and not self.reached(args.wait_for):
            last = self.statuses[-1].get("state") if self.statuses else "unknown"
            print(f"{say}state {args.wait_for} not reached within {wait:g} s (state {last})", file=sys.stderr)
            return EXIT_UNFINISHED
        return code


def cmd_send(args: argparse.Namespace) -> int:
    """Put the message on each vehicle's exact key (`--vehicle A,B` fans it out: one put per vehicle,
    all at once) and wait for each companion's outcome. Exit: the single vehicle's code; with several,
    0 when every one succeeded, else the code of the first vehicle (in the order given) that did not."""
    payload = sys.stdin.buffer.read() if args.file == "-" else Path(args.file).read_bytes()
    try:
        vehicles = vehicles_of(args.vehicle)
    except ValueError as exc:
        print(f"send: {exc}", file=sys.stderr)
        return EXIT_USAGE
    wait = DEFAULT_WAIT[args.key] if args.wait is None else args.wait
    session = client_session(args, wait)
    fleet = len(vehicles) > 1
    try:
        targets = [Target(session, args, v) for v in vehicles]
        for t in targets:
            # Which companion answers (this also lets the subscriptions reach it before the message).
            t.origin = Origin(session, t.base)
            if t.origin.companion is None:
                print(f"send: {t.vehicle + ': ' if fleet else ''}{t.origin.note}", file=sys.stderr)
        for t in targets:
            # A publisher says whether any subscriber matches its key: the companion's subscription
            # reaches this client only where access control lets this user publish there (Zenoh
            # drops a denied put silently, so this is how a denial can be told from silence).
            t.pub = session.declare_publisher(f"{t.base}/{args.key}")
            t.matched = [bool(t.pub.matching_status.matching)]
        for t in targets:  # the exact key of each vehicle, never a wildcard
            t.pub.put(payload)
        deadline = time.monotonic() + wait
        while time.monotonic() < deadline and not all(t.done for t in targets):
            time.sleep(0.05)
            for t in targets:
                if t.done:
                    continue
                t.show(fleet)
                t.code = outcome(args.key, t.events)
                if t.code is not None and (t.code != EXIT_OK or not args.wait_for):
                    t.done = True
                if t.code == EXIT_OK and t.reached(args.wait_for):
                    t.done = True
        codes: list[int] = []
        for t in targets:
            t.show(fleet)
            t.matched.append(bool(t.pub.matching_status.matching))
            for sub in t.subs:
                sub.undeclare()
            assert t.origin is not None
            ignored = t.origin.summary()
            if ignored:
                print(f"send: {t.vehicle + ': ' if fleet else ''}{ignored}", file=sys.stderr)
            t.pub.undeclare()
            codes.append(t.verdict(args, wait, f"send: {t.vehicle}: " if fleet else "send: "))
        if fleet:
            print("send: " + ", ".join(f"{t.vehicle} {c}" for t, c in zip(targets, codes, strict=True)),
                  file=sys.stderr)
        return next((c for c in codes if c != EXIT_OK), EXIT_OK)
    finally:
        session.close()
