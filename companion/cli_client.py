"""What the command-line clients (`send`, `watch`, `fleet`) share: a Zenoh client session,
their common arguments, the check of which companion answers (`Origin`), and the exit codes."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from typing import Any

from companion.config import ZenohConfig


def client_session(args: argparse.Namespace, patience: float = 0.0) -> Any:
    import zenoh

    from companion.wire.zenoh import zenoh_config

    zc = ZenohConfig(
        mode="client" if args.connect else "peer",
        connect=tuple(args.connect or ()),
        multicast_scouting=not args.connect,
        config_file=args.zenoh_config or "",
    )
    # A client started right after `python -m companion run &` waits for it to listen.
    deadline = time.monotonic() + patience
    said = False
    while True:
        try:
            return zenoh.open(zenoh_config(zc, listen=False))
        except zenoh.ZError:
            if time.monotonic() >= deadline:
                raise
            if not said:
                print(f"{args.command}: waiting for the companion at {', '.join(args.connect or ())}",
                      file=sys.stderr, flush=True)
                said = True
            time.sleep(0.5)


def add_client_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--vehicle", default="drone1",
                   help="the vehicle id (default drone1); send: several joined with ',' (A,B,C): one put on each "
                   "vehicle's exact key, all at once, and each one's outcome")
    p.add_argument("--prefix", default="bezier")
    p.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help="Zenoh endpoint of the companion or a router, e.g. tcp/127.0.0.1:7447 (repeatable); "
                   "without it, peers are found by multicast scouting")
    p.add_argument("--zenoh-config", metavar="FILE.json5", help="full Zenoh configuration (TLS, auth)")


class Origin:
    """Which companion a client addressed, and whether a sample comes from it.

    The companion answers the `<prefix>/<vehicle>/status` query and puts its Zenoh session id
    (`session`) in every status and event. A client asks once: exactly one session answering,
    with its own id in the body, is the companion; samples from then on must carry that id.
    Samples put on any other key expression than the exact one (`bezier/*/events`) are never
    taken. This catches stray and careless fakes; an id can be claimed by anyone who reaches
    the network, so only Zenoh authentication and access control stop a determined peer
    (docs/security.md)."""

    def __init__(self, session: Any, base: str, timeout: float = 1.0) -> None:
        import zenoh

        self.base = base
        self.ignored: dict[str, int] = {}
        found: dict[str, Any] = {}
        with contextlib.suppress(Exception):
            for reply in session.get(f"{base}/status", target=zenoh.QueryTarget.ALL,
                                     consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout):
                if reply.ok is None:
                    continue
                replier = getattr(reply.replier_id, "zid", reply.replier_id)
                body: Any = None
                with contextlib.suppress(ValueError):
                    body = json.loads(reply.ok.payload.to_bytes())
                found[str(replier)] = body.get("session") if isinstance(body, dict) else None
        honest = [z for z, said in found.items() if said == z]
        self.companion: str | None = honest[0] if len(honest) == 1 and len(found) == 1 else None
        if self.companion is not None:
            self.note = f"companion session {self.companion}"
        elif not found:
            self.note = ("no companion answered the status query: cannot check where status and events come "
                         "from (shown as received)")
        else:
            self.note = (f"{len(found)} sessions answer as {base} ({', '.join(sorted(found))}): cannot tell which "
                         "is the companion; status and events are shown unchecked")

    def accepts(self, topic: str, sample: Any, body: Any) -> bool:
        """The sample was put on the exact key and (when known) by the addressed companion."""
        key = str(sample.key_expr)
        if key != f"{self.base}/{topic}":
            why = f"put on {key!r}"
        elif self.companion is not None and (not isinstance(body, dict) or body.get("session") != self.companion):
            why = "not from the addressed companion"
        else:
            return True
        self.ignored[why] = self.ignored.get(why, 0) + 1
        return False

    def summary(self) -> str | None:
        if not self.ignored:
            return None
        return "ignored " + "; ".join(f"{n} sample(s) {why}" for why, n in self.ignored.items())


# `send` exit codes: it never says success for nothing.
EXIT_OK = 0  # accepted (a command: and completed; with --wait-for: and the state reached)
EXIT_REJECTED = 1  # the message was rejected (invalid, or cannot be done now: `rejected`)
EXIT_USAGE = 2  # bad arguments, unreadable file, Zenoh error
EXIT_NO_ANSWER = 3  # no companion answered within --wait (nobody serves that vehicle?)
EXIT_REFUSED = 4  # the command was refused by the companion (state, no position estimate, ...)
EXIT_DENIED = 5  # the autopilot denied it (or did not answer it)
EXIT_UNFINISHED = 6  # accepted, but not completed (or --wait-for STATE not reached) within --wait
# The companion is heard, but its subscription to the key never reached this client: Zenoh's
# access control denies this user publishing there (or nothing serves that key).
EXIT_ACCESS_DENIED = 7
