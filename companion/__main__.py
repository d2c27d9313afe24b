"""`python -m companion`: run the service, send a message, watch a vehicle, or the demo.

    python -m companion run --config FILE.toml
    python -m companion --print-default-config
    python -m companion send KEY FILE.json [--vehicle ID[,ID...]] [--connect tcp/127.0.0.1:7447]
    python -m companion watch [--vehicle ID] [--connect ...] [--telemetry]
    python -m companion demo ...
    python -m companion replay FILE.mcap [--from T] [--until T]
    python -m companion recording summary FILE.mcap
    python -m companion router --listen tcp/HOST:PORT [--config FILE.json5]
    python -m companion fleet [--connect ...]

This module only parses the arguments and dispatches: each subcommand lives in its own
module (`cli_run.py`, `cli_send.py`, `cli_watch.py`, `cli_fleet.py`; what the clients share
in `cli_client.py`), `replay`, `recording` and `router` in theirs.
"""

from __future__ import annotations

import argparse
import sys

from companion.cli_client import add_client_args
from companion.cli_fleet import cmd_fleet
from companion.cli_run import cmd_run
from companion.cli_send import cmd_send
from companion.cli_watch import cmd_watch
from companion.config import config_to_toml
from companion.wire.keys import INBOUND

KEYS = INBOUND


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m companion", description="bezier-companion service")
    p.add_argument("--print-default-config", action="store_true", help="print every option with its default as TOML")
    sub = p.add_subparsers(dest="command")
    r = sub.add_parser("run", help="run the service")
    r.add_argument("--config", metavar="FILE.toml")
    r.add_argument("--quiet", action="store_true")
    r.add_argument("--print-default-config", action="store_true")
    s = sub.add_parser("send", help="publish a JSON message to a vehicle")
    s.add_argument("key", choices=KEYS)
    s.add_argument("file", help="JSON file, or - for stdin")
    s.add_argument("--wait", type=float, default=None,
                   help="seconds to wait for the outcome (default: 30 for a command, which runs its whole "
                   "sequence, and a mission; 10 otherwise). Exit 0 accepted (a command: and completed), "
                   "1 rejected, 3 no companion answered, 4 refused, 5 denied by the autopilot, 6 not done in time, "
                   "7 denied by access control (the companion is heard but does not receive this key)")
    s.add_argument("--wait-for", metavar="STATE", help="after success, also wait until the status says STATE "
                   "(e.g. READY, HOLDING); exit 6 if it does not within --wait")
    add_client_args(s)
    w = sub.add_parser("watch", help="print status and events")
    w.add_argument("--telemetry", action="store_true")
    w.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: never)")
    w.add_argument("--silence", type=float, default=3.0, metavar="SECONDS",
                   help="say so on stderr when nothing has been heard for this long (default 3)")
    w.add_argument("--wait-for", metavar="STATE", help="exit 0 once the status says STATE (6 if --duration ends "
                   "first); 'link': once the autopilot is heard; 'home': once it reported a valid home (ready)")
    add_client_args(w)
    f = sub.add_parser("fleet", help="list the vehicles present (liveliness) with their state, mission and progress")
    f.add_argument("--prefix", default="bezier")
    f.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help="Zenoh endpoint of the fleet's router (or a companion), e.g. tcp/127.0.0.1:7447 (repeatable)")
    f.add_argument("--zenoh-config", metavar="FILE.json5", help="full Zenoh configuration (TLS, auth)")
    f.add_argument("--wait", type=float, default=2.0, metavar="SECONDS",
                   help="how long to look for vehicles (default 2); exit 3 if none is present")
    f.add_argument("--json", action="store_true", help="one JSON object per vehicle, with its whole status")
    sub.add_parser("demo", help="a scripted demo flight against the mock autopilot (= python -m demo)",
                   add_help=False)
    sub.add_parser("replay", help="run a recording's plans again and compare them bit for bit", add_help=False)
    sub.add_parser("recording", help="recording summary FILE.mcap: what a recorded flight holds", add_help=False)
    sub.add_parser("router", help="run a Zenoh router for a fleet (docs/fleet.md)", add_help=False)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] == "replay":
        from companion.replay_cli import main as replay_main

        return replay_main(argv[1:])
    if argv and argv[0] == "router":
        from companion.router import main as router_main

        return router_main(argv[1:])
    if argv and argv[0] == "recording":
        from companion.recording import main as recording_main

        return recording_main(argv[1:])
    if argv and argv[0] == "demo":
        # the demo lives in the top-level `demo` package (a client of the service); this
        # subcommand is kept as an alias of `python -m demo`
        from demo.run import main as demo_main

        return int(demo_main(argv[1:], prog="python -m companion demo") or 0)
    args = build_parser().parse_args(argv)
    if args.print_default_config:
        sys.stdout.write(config_to_toml())
        return 0
    if args.command == "run":
        return cmd_run(args)
    if args.command in ("send", "watch", "fleet"):
        import zenoh

        try:
            return {"send": cmd_send, "watch": cmd_watch, "fleet": cmd_fleet}[args.command](args)
        except zenoh.ZError as exc:
            print(f"zenoh: {exc}", file=sys.stderr)
            return 2
        except OSError as exc:
            print(f"{args.command}: {exc}", file=sys.stderr)
            return 2
    build_parser().print_help()
    return 2


if __name__ == "__main__":
    sys.exit(main())
