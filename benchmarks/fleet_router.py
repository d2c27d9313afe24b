"""The fleet's traffic through one router (issue 24, item 6): message rate per vehicle, the router's
cost per message delivered, the delivery latency, and what 1,000 vehicles would need.

A real router (`python -m companion router`, open loopback endpoint) and N vehicles as Zenoh client
sessions of this process. Each vehicle does what a companion with `[fleet] separation` does on the
wire: puts its committed trajectory (a real 12-segment plan with its fleet part, ~the size a
companion publishes) on `bezier/<v>/trajectory` once a second (REPUBLISH) with its send time as
the attachment, and subscribes to `bezier/*/trajectory`. Measured over `--seconds`: deliveries
per second, the router's CPU (utime + stime from /proc) per delivery, latency from the send time
to the subscriber's callback, and a receiver's own cost per message (parse + read_claim, what
`Deconfliction.on_trajectory` does before anything else). Then the 1,000-vehicle estimate from
those figures, all-to-all and with subscriptions kept to a neighbourhood.

    .venv/bin/python benchmarks/fleet_router.py [--vehicles 5 10 20 40] [--seconds 10] [--json OUT]
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import threading
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

import zenoh

from companion.traffic import read_claim
from companion.wire.encode import encode_trajectory
from planner_core import Bounds, plan_mission

TICK = os.sysconf("SC_CLK_TCK")
REPUBLISH = 1.0  # s: companion.deconfliction.REPUBLISH


def _port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _cpu(pid: int) -> float:
    with open(f"/proc/{pid}/stat") as f:
        parts = f.read().rsplit(")", 1)[1].split()
    return (int(parts[11]) + int(parts[12])) / TICK  # utime + stime, s


def message(vehicle: str) -> bytes:
    """A committed trajectory as a companion publishes it: a 12-waypoint plan, fleet part with
    two certificates' worth of numbers."""
    rng = np.random.default_rng(abs(hash(vehicle)) % 2**32)
    wps = np.cumsum(np.vstack([[0.0, 0.0, -3.0], rng.normal(size=(11, 3)) * [6.0, 6.0, 0.3]]), axis=0)
    mp = plan_mission(wps, Bounds.symmetric(5.0, 4.0, 15.0, 60.0), timing="default")
    assert mp.ok and mp.trajectory is not None, mp.message
    cert = {"times": list(np.linspace(0, 30, 24)), "normals": [[0.6, 0.8, 0.0]] * 23, "offsets": [1.5] * 23,
            "separation": 3.0, "clock_tolerance": 0.05, "speed_a": 8.0, "speed_b": 8.0}
    fleet = {"commit": "committed", "seq": 7, "vehicle": vehicle, "priority": 0, "time_base": time.time(),
             "frame": "fleet-ned", "offset_ned": [10.0, 4.0, -1.6], "rotation": np.eye(3).tolist(), "radius": 0.3,
             "bound_speed": 8.66, "separation": 3.0, "clock_tolerance": 0.05, "expires": None,
             "certificates": {"a": {"seq": 3, "certificate": cert}, "b": {"seq": 4, "certificate": cert}}}
    return encode_trajectory(mp.trajectory, fleet)


def _session(port: int) -> Any:
    c = zenoh.Config()
    c.insert_json5("mode", '"client"')
    c.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{port}"]))
    c.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(c)


def run(n: int, seconds: float) -> dict[str, Any]:
    port = _port()
    router = subprocess.Popen([sys.executable, "-m", "companion", "router", "--listen", f"tcp/127.0.0.1:{port}"],
                              stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                              cwd=Path(__file__).resolve().parents[1])
    sessions: list[Any] = []
    lock = threading.Lock()
    got: list[float] = []  # latencies (s) of deliveries inside the window
    window = [False]
    try:
        time.sleep(1.0)
        names = [f"v{i:03d}" for i in range(n)]
        bodies = {v: message(v) for v in names}
        pubs = {}
        for v in names:
            s = _session(port)
            sessions.append(s)

            def on(sample: Any, me: str = v) -> None:
                arrived = time.time()
                if str(sample.key_expr).split("/")[1] == me or not window[0]:
                    return
                sent = json.loads(sample.attachment.to_bytes())["sent"]
                with lock:
                    got.append(arrived - sent)

            s.declare_subscriber("bezier/*/trajectory", on)
            pubs[v] = s.declare_publisher(f"bezier/{v}/trajectory")
        time.sleep(1.0)
        stop = threading.Event()

        def publish() -> None:
            k = 0
            t0 = time.monotonic()
            while not stop.is_set():
                v = names[k % n]
                pubs[v].put(bodies[v], attachment=json.dumps({"sent": time.time()}).encode())
                k += 1
                nxt = t0 + k * REPUBLISH / n  # every vehicle once per REPUBLISH, staggered
                time.sleep(max(0.0, nxt - time.monotonic()))

        th = threading.Thread(target=publish, daemon=True)
        th.start()
        time.sleep(1.0)
        cpu0, t0 = _cpu(router.pid), time.monotonic()
        window[0] = True
        time.sleep(seconds)
        window[0] = False
        cpu1, t1 = _cpu(router.pid), time.monotonic()
        stop.set()
        th.join(5)
        lat = np.asarray(got) * 1000.0
        delivered = len(lat) / (t1 - t0)
        size = float(np.mean([len(b) for b in bodies.values()]))
        # a receiver's own cost per message: what on_trajectory does first
        body = bodies[names[0]]
        reps = 200
        c0 = time.perf_counter()
        for _ in range(reps):
            read_claim(json.loads(body), names[0])
        recv_ms = (time.perf_counter() - c0) / reps * 1000.0
        return {"vehicles": n, "bytes": size, "expected_per_s": n * (n - 1) / REPUBLISH,
                "delivered_per_s": delivered, "router_cpu": (cpu1 - cpu0) / (t1 - t0),
                "router_us_per_delivery": (cpu1 - cpu0) / max(len(lat), 1) * 1e6,
                "latency_p50_ms": float(np.percentile(lat, 50)) if lat.size else float("nan"),
                "latency_p99_ms": float(np.percentile(lat, 99)) if lat.size else float("nan"),
                "latency_max_ms": float(lat.max()) if lat.size else float("nan"),
                "receive_ms_per_message": recv_ms}
    finally:
        for s in sessions:
            s.close()
        router.terminate()
        router.wait(10)


def estimate(rows: list[dict[str, Any]], fleet: int = 1000, near: int = 20) -> dict[str, float]:
    """1,000 vehicles from the largest measured row: all-to-all, and with each vehicle subscribed
    only to the trajectories of the `near` vehicles around it (key space by area, not built)."""
    r = max(rows, key=lambda x: x["vehicles"])
    per_delivery = r["router_us_per_delivery"] * 1e-6
    out = {}
    for name, fan in (("all", fleet - 1), ("near", near)):
        deliveries = fleet * fan / REPUBLISH
        out[f"{name}_deliveries_per_s"] = deliveries
        out[f"{name}_router_cores"] = deliveries * per_delivery
        out[f"{name}_router_MB_per_s"] = deliveries * r["bytes"] / 1e6
        out[f"{name}_vehicle_in_kB_per_s"] = fan * r["bytes"] / REPUBLISH / 1e3
        out[f"{name}_vehicle_cpu_share"] = fan / REPUBLISH * r["receive_ms_per_message"] / 1000.0
    return out


def format_rows(rows: list[dict[str, Any]], est: dict[str, float]) -> str:
    head = ["vehicles", "message [kB]", "deliveries/s (expected)", "router CPU [cores]", "router us/delivery",
            "latency p50 / p99 / max [ms]", "receiver ms/message"]
    body = [[f"{r['vehicles']}", f"{r['bytes'] / 1e3:.1f}", f"{r['delivered_per_s']:.0f} ({r['expected_per_s']:.0f})",
             f"{r['router_cpu']:.3f}", f"{r['router_us_per_delivery']:.0f}",
             f"{r['latency_p50_ms']:.1f} / {r['latency_p99_ms']:.1f} / {r['latency_max_ms']:.1f}",
             f"{r['receive_ms_per_message']:.2f}"] for r in rows]
    widths = [max(len(x) for x in col) for col in zip(head, *body, strict=True)]
    lines = [" | ".join(x.ljust(w) for x, w in zip(head, widths, strict=True)),
             "-+-".join("-" * w for w in widths)]
    lines += [" | ".join(x.ljust(w) for x, w in zip(row, widths, strict=True)) for row in body]
    lines.append("")
    lines.append("1,000 vehicles, from the largest row (one put per vehicle per second):")
    for name, what in (("all", "every vehicle subscribed to every other (as today)"),
                       ("near", "each subscribed to the 20 vehicles around it (a key per area: not built)")):
        lines.append(f"  {what}: {est[name + '_deliveries_per_s']:.3g} deliveries/s through the routers, "
                     f"~{est[name + '_router_cores']:.2g} router cores, {est[name + '_router_MB_per_s']:.3g} MB/s; "
                     f"per vehicle {est[name + '_vehicle_in_kB_per_s']:.3g} kB/s in and "
                     f"{100 * est[name + '_vehicle_cpu_share']:.2g} % of a core to read them")
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--vehicles", type=int, nargs="+", default=[5, 10, 20, 40])
    p.add_argument("--seconds", type=float, default=10.0)
    p.add_argument("--json", type=Path, default=None)
    a = p.parse_args(argv)
    rows = [run(n, a.seconds) for n in a.vehicles]
    est = estimate(rows)
    print(format_rows(rows, est))
    if a.json is not None:
        a.json.write_text(json.dumps({"rows": rows, "estimate": est, "date": time.strftime("%Y-%m-%d")}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
