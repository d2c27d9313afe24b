"""`python -m companion router`: a Zenoh router for a fleet (docs/fleet.md).

The router is Zenoh's own (the zenoh library opened in router mode); the project adds no
transport of its own. Companions join it as clients (`[zenoh] mode = "client"`, `connect`),
operators' tools too. The secured configuration it ships (config/zenoh-router-fleet.json5)
turns on mutual TLS, user/password and access control: vehicle `v` may put only under
`<prefix>/v/**` and read the fleet's trajectories and liveliness; operators command and read
every vehicle; observers read.
"""

from __future__ import annotations

import argparse
import json
import signal
import sys
import threading
from typing import Any


def router_config(listen: list[str], config_file: str | None) -> Any:
    """A zenoh.Config in router mode: the JSON5 file (if given) as the base, `listen` over it.

    Without a file, multicast scouting is off: routers are found by the endpoints they are
    given (a router mesh lists its neighbours in `connect`, docs/fleet.md)."""
    import zenoh

    cfg = zenoh.Config.from_file(config_file) if config_file else zenoh.Config()
    cfg.insert_json5("mode", json.dumps("router"))
    if listen:
        cfg.insert_json5("listen/endpoints", json.dumps(listen))
    if not config_file:
        cfg.insert_json5("scouting/multicast/enabled", "false")
    return cfg


def run_router(listen: list[str], config_file: str | None, stop: threading.Event) -> int:
    """Run until `stop` is set; 0, or 1 when the router cannot start."""
    import zenoh

    try:
        cfg = router_config(listen, config_file)
        session: Any = zenoh.open(cfg)
    except zenoh.ZError as exc:
        print(f"router: {exc}", file=sys.stderr, flush=True)
        return 1
    try:
        try:
            endpoints = json.loads(cfg.get_json("listen/endpoints"))
        except Exception:  # a zenoh without that key
            endpoints = listen
        print(f"router {session.zid()} listening on {', '.join(map(str, endpoints)) or 'defaults'}",
              file=sys.stderr, flush=True)
        while not stop.wait(0.5):
            pass
    finally:
        session.close()
    return 0


def main(argv: list[str]) -> int:
    p = argparse.ArgumentParser(prog="python -m companion router",
                                description="run a Zenoh router for a fleet (docs/fleet.md)")
    p.add_argument("--listen", action="append", default=[], metavar="ENDPOINT",
                   help="where companions and operators connect, e.g. tcp/0.0.0.0:7447 or tls/0.0.0.0:7447 "
                   "(repeatable; over the file's listen endpoints)")
    p.add_argument("--config", metavar="FILE.json5",
                   help="a Zenoh configuration (the shipped config/zenoh-router-fleet.json5: mutual TLS, "
                   "user/password, access control per vehicle)")
    args = p.parse_args(argv)
    if not args.listen and not args.config:
        p.error("give --listen ENDPOINT (and/or --config FILE)")
    stop = threading.Event()

    def on_signal(signum: int, frame: Any) -> None:
        stop.set()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    return run_router(args.listen, args.config, stop)
