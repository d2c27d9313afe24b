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
from companion.wire.keys import INBOUND

KEYS = INBOUND


def _client_session(args: argparse.Namespace, patience: float = 0.0) -> Any:
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


def _add_client_args(p: argparse.ArgumentParser) -> None:
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

# How long `send` waits by default: a command runs its whole sequence (takeoff: ~10 s).
DEFAULT_WAIT = {"command": 30.0, "mission": 30.0, "obstacles": 10.0, "change": 10.0}


def _outcome(key: str, events: list[dict[str, Any]]) -> int | None:
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


class _Target:
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
    session = _client_session(args, wait)
    fleet = len(vehicles) > 1
    try:
        targets = [_Target(session, args, v) for v in vehicles]
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
                t.code = _outcome(args.key, t.events)
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


def fleet_list(session: Any, prefix: str, timeout: float = 1.0) -> list[dict[str, Any]]:
    """The vehicles present (a liveliness token at `<prefix>/<vehicle>/alive`), each with the
    status its companion answers (`<prefix>/<vehicle>/status`, checked as `send` checks it: the
    exact key, one session whose id is in the body), in vehicle order."""
    from companion.wire.keys import ALIVE

    present: set[str] = set()
    with contextlib.suppress(Exception):
        for reply in session.liveliness().get(f"{prefix}/*/{ALIVE}", timeout=timeout):
            if reply.ok is None:
                continue
            parts = str(reply.ok.key_expr).split("/")
            if len(parts) == len(prefix.split("/")) + 2 and parts[-1] == ALIVE:
                present.add(parts[-2])
    out: list[dict[str, Any]] = []
    for vehicle in sorted(present):
        base = f"{prefix}/{vehicle}"
        status: dict[str, Any] | None = None
        clock: tuple[float, float] | None = None
        origin = Origin(session, base, timeout=timeout)
        if origin.companion is not None:
            with contextlib.suppress(Exception):
                asked = time.time()
                for reply in session.get(f"{base}/status", timeout=timeout):
                    answered = time.time()
                    if reply.ok is None or str(reply.ok.key_expr) != f"{base}/status":
                        continue
                    body = json.loads(reply.ok.payload.to_bytes())
                    if isinstance(body, dict) and body.get("session") == origin.companion:
                        status = body
                        # the status is made when asked: its `time` (the vehicle's clock, ms) against
                        # the middle of the round trip here, give or take half of it
                        if isinstance(body.get("time"), int | float):
                            half = (answered - asked) / 2.0
                            clock = (float(body["time"]) - (asked + half), half + 0.0005)
                        break
        out.append({"vehicle": vehicle, "status": status, "note": None if status is not None else origin.note,
                    "clock_offset_ms": None if clock is None else round(clock[0] * 1000.0, 1),
                    "clock_uncertainty_ms": None if clock is None else round(clock[1] * 1000.0, 1)})
    return out


FLEET_COLUMNS = ("vehicle", "state", "mission", "progress", "armed", "link", "frame", "clock_ms")


def _fleet_row(entry: dict[str, Any]) -> dict[str, Any]:
    st = entry["status"] or {}
    fleet = st.get("fleet") if isinstance(st.get("fleet"), dict) else {}
    return {"vehicle": entry["vehicle"], "state": st.get("state", "?"), "mission": st.get("mission"),
            "progress": st.get("progress"), "armed": st.get("armed"), "link": st.get("link"),
            "frame": fleet.get("frame") if fleet else None, "clock_ms": entry.get("clock_offset_ms")}


def clock_warning(entry: dict[str, Any]) -> str | None:
    """The vehicle's clock is off this computer's by more than its `[fleet] clock_tolerance`
    (beyond what the round trip leaves unknown): what to say, else None."""
    st = entry["status"] or {}
    fleet = st.get("fleet") if isinstance(st.get("fleet"), dict) else None
    off, unsure = entry.get("clock_offset_ms"), entry.get("clock_uncertainty_ms")
    if fleet is None or off is None or unsure is None or not isinstance(fleet.get("clock_tolerance"), int | float):
        return None
    tolerance_ms = float(fleet["clock_tolerance"]) * 1000.0
    if abs(off) - unsure <= tolerance_ms:
        return None
    return (f"{entry['vehicle']}: its clock is {off:+.0f} ms (+-{unsure:.0f}) off this computer's, more than its "
            f"[fleet] clock_tolerance ({tolerance_ms:.0f} ms): check NTP/chrony/PTP on both")


def cmd_fleet(args: argparse.Namespace) -> int:
    """List the vehicles present (liveliness) with their state, mission and progress (status).
    Exit 0 when at least one vehicle is present, 3 when none is."""
    session = _client_session(args, args.wait)
    try:
        deadline = time.monotonic() + args.wait
        while True:
            entries = fleet_list(session, args.prefix, timeout=min(1.0, max(args.wait, 0.1)))
            if entries or time.monotonic() >= deadline:
                break
            time.sleep(0.2)
    finally:
        session.close()
    if args.json:
        for e in entries:
            print(json.dumps({**_fleet_row(e), "clock_uncertainty_ms": e.get("clock_uncertainty_ms"),
                              "status": e["status"], "note": e["note"]}), flush=True)
    else:
        rows = [[_cell(v, k) for k, v in _fleet_row(e).items()] for e in entries]
        widths = [max([len(c)] + [len(r[i]) for r in rows]) for i, c in enumerate(FLEET_COLUMNS)]
        print("  ".join(c.ljust(w) for c, w in zip(FLEET_COLUMNS, widths, strict=True)).rstrip())
        for r in rows:
            print("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip())
    for e in entries:
        if e["note"] and not args.json:
            print(f"fleet: {e['vehicle']}: {e['note']}", file=sys.stderr)
        warning = clock_warning(e)
        if warning is not None:
            print(f"fleet: {warning}", file=sys.stderr)
    if not entries:
        print(f"fleet: no vehicle present under {args.prefix}/*/alive within {args.wait:g} s (--prefix and "
              "--connect must match the fleet's router or companions)", file=sys.stderr)
        return EXIT_NO_ANSWER
    return 0


def _cell(v: Any, column: str) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if column == "progress" and isinstance(v, int | float):
        return f"{v:.0%}"
    if column == "clock_ms" and isinstance(v, int | float):
        return f"{v:+.0f}"
    return str(v)


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
    session = _client_session(args, args.duration or 30.0)
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
    _add_client_args(s)
    w = sub.add_parser("watch", help="print status and events")
    w.add_argument("--telemetry", action="store_true")
    w.add_argument("--duration", type=float, default=0.0, help="stop after this many seconds (0: never)")
    w.add_argument("--silence", type=float, default=3.0, metavar="SECONDS",
                   help="say so on stderr when nothing has been heard for this long (default 3)")
    w.add_argument("--wait-for", metavar="STATE", help="exit 0 once the status says STATE (6 if --duration ends "
                   "first); 'link': once the autopilot is heard; 'home': once it reported a valid home (ready)")
    _add_client_args(w)
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
        from companion.replay import main as replay_main

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
