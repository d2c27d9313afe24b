"""`python -m companion run`: load the configuration and run the service until a signal, then
hand the vehicle over (a second signal gives the hand-over up)."""

from __future__ import annotations

import argparse
import asyncio
import logging
import signal
import sys

from companion.config import Config, ConfigError, load_config

RECORDING_ENV = "BEZIER_COMPANION_RECORDING"


def recording_default(cfg: Config, path: str | None) -> Config:
    """`[recording] path` from $BEZIER_COMPANION_RECORDING (the systemd unit's state directory)
    when the configuration file does not set it; `path = ""` in the file keeps recording off."""
    import dataclasses
    import os
    import tomllib

    default = os.environ.get(RECORDING_ENV, "")
    if not default:
        return cfg
    if path:
        with open(path, "rb") as fh:
            if "path" in tomllib.load(fh).get("recording", {}):
                return cfg
    return dataclasses.replace(cfg, recording=dataclasses.replace(cfg.recording, path=default))


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
        cfg = recording_default(cfg, args.config)
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
    from planner_core.window import aot_unavailable, kernel_build

    # No numba in this process (urgent replans, local replans, stops; missions too with executor
    # "thread"): numba and LLVM would add ~105 MB resident (benchmarks/footprint.py). The
    # compiled pass's AOT build (no numba, <1 MB) where `make setup` built it, else the numpy
    # path. Planner processes start fresh and follow [planner] compiled. Decided here, by the
    # process entry point, not by Service: it is process-wide.
    kernel_build("aot")
    why_not = aot_unavailable()
    if why_not is not None:
        logging.getLogger("companion").warning("planning on the numpy path (~10x slower a window step than "
                                               "the compiled pass): %s", why_not)

    async def main() -> bool:
        # First SIGINT/SIGTERM: brake, hand the vehicle over to the autopilot, exit 0 once it
        # confirms. A second one: give the hand-over up and exit at once (status 1).
        stop, abandon = asyncio.Event(), asyncio.Event()
        loop = asyncio.get_running_loop()

        def on_signal(name: str) -> None:
            if stop.is_set():
                logging.getLogger("companion").warning("%s again: exiting now, without the hand-over", name)
                abandon.set()
            else:
                logging.getLogger("companion").info("%s: stopping (hand-over to the autopilot first)", name)
                stop.set()

        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, on_signal, sig.name)
        return await run(cfg, stop=stop, abandon=abandon)

    import zenoh

    try:
        handed_over = asyncio.run(main())
    except zenoh.ZError as exc:
        print(f"zenoh: {exc}", file=sys.stderr)
        return 1
    except OSError as exc:
        print(f"mavlink {cfg.mavlink.url}: {exc}", file=sys.stderr)
        return 1
    except Exception as exc:  # an internal failure: the vehicle was handed over first
        logging.getLogger("companion").critical("stopped on an internal failure: %r", exc, exc_info=exc)
        return 3
    return 0 if handed_over else 1
