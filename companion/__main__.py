"""`python -m companion`: run the service, send a message, watch a vehicle, or the demo.

    python -m companion run --config FILE.toml
    python -m companion --print-default-config
    python -m companion send KEY FILE.json [--vehicle ID] [--connect tcp/127.0.0.1:7447]
    python -m companion watch [--vehicle ID] [--connect ...] [--telemetry]
    python -m companion demo ...
"""

from __future__ import annotations

import argparse
import asyncio
import contextlib
import json
import logging
import signal
import sys
import time
from pathlib import Path
from typing import Any

from companion.config import Config, ConfigError, ZenohConfig, config_to_toml, load_config

KEYS = ("mission", "obstacles", "change", "command")


def _client_session(args: argparse.Namespace) -> Any:
    import zenoh

    from companion.wire.zenoh import zenoh_config

    zc = ZenohConfig(
        mode="client" if args.connect else "peer",
        connect=tuple(args.connect or ()),
        multicast_scouting=not args.connect,
        config_file=args.zenoh_config or "",
    )
    return zenoh.open(zenoh_config(zc, listen=False))


def _add_client_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--vehicle", default="drone1")
    p.add_argument("--prefix", default="bezier")
    p.add_argument("--connect", action="append", metavar="ENDPOINT",
                   help="Zenoh endpoint of the companion or a router, e.g. tcp/127.0.0.1:7447 (repeatable); "
                   "without it, peers are found by multicast scouting")
    p.add_argument("--zenoh-config", metavar="FILE.json5", help="full Zenoh configuration (TLS, auth)")


def cmd_send(args: argparse.Namespace) -> int:
    payload = sys.stdin.buffer.read() if args.file == "-" else Path(args.file).read_bytes()
    session = _client_session(args)
    try:
        events: list[dict[str, Any]] = []
        sub = None
        if args.wait > 0:
            def on_event(sample: Any) -> None:
                with contextlib.suppress(ValueError):
                    events.append(json.loads(sample.payload.to_bytes()))

            sub = session.declare_subscriber(f"{args.prefix}/{args.vehicle}/events", on_event)
            time.sleep(0.3)  # let the subscription reach the companion before the message
        session.put(f"{args.prefix}/{args.vehicle}/{args.key}", payload)
        deadline = time.monotonic() + args.wait
        while time.monotonic() < deadline:
            time.sleep(0.05)
            done = [e for e in events if e.get("key") == args.key and e.get("type") in ("accepted", "rejected", "refused")]
            if done:
                for e in events:
                    print(json.dumps(e))
                return 0 if done[-1]["type"] == "accepted" else 1
        for e in events:
            print(json.dumps(e))
        if sub is not None:
            sub.undeclare()
        return 0
    finally:
        session.close()


def cmd_watch(args: argparse.Namespace) -> int:
    session = _client_session(args)
    topics = ["status", "events"] + (["telemetry"] if args.telemetry else [])

    def show(sample: Any) -> None:
        key = str(sample.key_expr).rsplit("/", 1)[-1]
        text = sample.payload.to_bytes().decode("utf-8", "replace")
        print(f"{key} {text}", flush=True)

    subs = [session.declare_subscriber(f"{args.prefix}/{args.vehicle}/{t}", show) for t in topics]
    deadline = time.monotonic() + args.duration if args.duration else None
    try:
        while deadline is None or time.monotonic() < deadline:
            time.sleep(0.1)
    except KeyboardInterrupt:
        pass
    finally:
        for s in subs:
            s.undeclare()
        session.close()
    return 0


def cmd_run(args: argparse.Namespace) -> int:
    from companion import rtsched

    try:
        # First, before anything starts a thread: realtime scheduling from the service manager
        # (CPUSchedulingPolicy=) is kept for the setpoint thread only.
        inherited = rtsched.reserve()
    except rtsched.RealtimeError as exc:
        print(f"scheduling: {exc}", file=sys.stderr)
        return 2
    try:
        cfg = load_config(args.config) if args.config else Config()
    except (ConfigError, OSError) as exc:
        print(f"config error: {exc}", file=sys.stderr)
        return 2
    logging.basicConfig(level=logging.INFO if not args.quiet else logging.WARNING,
                        format="%(asctime)s %(name)s %(levelname)s %(message)s")
    if inherited is not None:
        logging.getLogger("companion").info("started under SCHED_%s: kept for the setpoint thread only",
                                            inherited.upper())
    import faulthandler

    # `kill -USR1 PID` dumps every thread's stack: how to see where a stuck service is.
    faulthandler.register(signal.SIGUSR1, all_threads=True)
    from companion.service import run

    if cfg.planner.executor == "process":
        from planner_core import disable_kernel

        # Missions are planned by worker processes (which use the compiled pass); what this
        # process plans itself (local replans, stops) is a few jets at a time, so the numpy
        # path there keeps numba and LLVM (~150 MB resident) out of the service process.
        # Decided here, by the process entry point, not by Service: it is process-wide.
        disable_kernel("companion service process: long plans run in the planner workers")

    async def main() -> None:
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        await run(cfg, stop=stop)

    import zenoh

    try:
        asyncio.run(main())
    except zenoh.ZError as exc:
        print(f"zenoh: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"mavlink {cfg.mavlink.url}: {exc}", file=sys.stderr)
        return 1
    return 0


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
    s.add_argument("--wait", type=float, default=2.0, help="seconds to wait for the accepted/rejected event (0: none)")
    _add_client_args(s)
    w = sub.add_parser("watch", help="print status and events")
    w.add_argument("--telemetry", action="store_true")
    w.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: never)")
    _add_client_args(w)
    sub.add_parser("demo", help="a scripted demo flight against the mock autopilot (= python -m demo)",
                   add_help=False)
    return p


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
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
    if args.command in ("send", "watch"):
        import zenoh

        try:
            return cmd_send(args) if args.command == "send" else cmd_watch(args)
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
