"""Service benchmark: setpoint timing, pop-up-obstacle latency, memory and CPU of the companion.

Runs the real chain on loopback (mock autopilot, companion service, a Zenoh peer) at 50 Hz and
100 Hz. While the vehicle flies a mission, this script keeps the companion's planner busy with
1000-waypoint plan requests (the `plan` queryable) and publishes pop-up obstacles next to the path.

A small relay process sits on the MAVLink link (companion -> relay -> mock) and stamps every
SET_POSITION_TARGET_LOCAL_NED with CLOCK_MONOTONIC, which all processes on this machine share, so:
- setpoint jitter is |arrival interval - 1/rate| at the relay (it includes loopback and relay
  scheduling noise, so it overstates the companion's own jitter slightly);
- obstacle latency is from our `put` to the first setpoint the relay forwards after the replanned
  trajectory was announced on Zenoh (so it includes up to one setpoint period of waiting).

Targets (at 50 Hz): jitter p99 <= 2 ms and max <= 10 ms, latency median <= 20 ms, RSS <= 150 MB.

    python benchmarks/service.py [--rates 50 100] [--flight 24] [--json out/bench/service.json]
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

MSG_SET_POSITION_TARGET_LOCAL_NED = 84
TARGETS = {"jitter_p99_ms": 2.0, "jitter_max_ms": 10.0, "latency_median_ms": 20.0, "rss_max_mb": 150.0}


# --- the relay (runs as its own process: `service.py --relay ...`) -----------------------------


def _msgid(packet: bytes) -> int | None:
    if len(packet) >= 10 and packet[0] == 0xFD:
        return int.from_bytes(packet[7:10], "little")
    if len(packet) >= 6 and packet[0] == 0xFE:
        return packet[5]
    return None


def relay(listen_port: int, target_port: int, out_path: str) -> int:
    """Forward UDP both ways; record the arrival time of every setpoint from the companion."""
    up = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # the companion talks to this one
    up.bind(("127.0.0.1", listen_port))
    down = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)  # and we talk to the mock from this
    down.bind(("127.0.0.1", 0))
    target = ("127.0.0.1", target_port)
    stamps: list[float] = []
    peer: list[tuple[str, int]] = []
    stop = threading.Event()

    def dump(*_: Any) -> None:
        stop.set()

    signal.signal(signal.SIGTERM, dump)
    signal.signal(signal.SIGINT, dump)

    def back() -> None:
        down.settimeout(0.2)
        while not stop.is_set():
            try:
                data = down.recv(65536)
            except OSError:
                continue
            if peer:
                up.sendto(data, peer[0])

    threading.Thread(target=back, daemon=True).start()
    up.settimeout(0.2)
    while not stop.is_set():
        try:
            data, addr = up.recvfrom(65536)
        except OSError:
            continue
        now = time.monotonic()
        if not peer:
            peer.append(addr)
        # a UDP datagram from pymavlink carries exactly one message
        if _msgid(data) == MSG_SET_POSITION_TARGET_LOCAL_NED:
            stamps.append(now)
        down.sendto(data, target)
    Path(out_path).write_text(json.dumps(stamps))
    return 0


# --- measurements ------------------------------------------------------------------------------


@dataclass
class ProcSampler:
    """RSS and CPU time of a process from /proc (Linux)."""

    pid: int
    rss: list[float] = field(default_factory=list)
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    def cpu_seconds(self) -> float:
        fields = Path(f"/proc/{self.pid}/stat").read_text().rsplit(")", 1)[1].split()
        return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")

    def rss_mb(self) -> float:
        for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        return float("nan")

    def peak_rss_mb(self) -> float:
        for line in Path(f"/proc/{self.pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
        return float("nan")

    def start(self) -> None:
        def run() -> None:
            while not self._stop.wait(0.25):
                with contextlib.suppress(OSError):
                    self.rss.append(self.rss_mb())

        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()


def big_mission(n: int = 1000, seed: int = 1) -> dict[str, Any]:
    """A 1000-waypoint random walk (NED, 2-4 m up, no obstacles) for the planner to chew on."""
    rng = np.random.default_rng(seed)
    steps = rng.normal(size=(n - 1, 3)) * [2.0, 2.0, 0.3]
    wps = np.cumsum(np.vstack([[0.0, 0.0, -3.0], steps]), axis=0)
    wps[:, :2] = np.clip(wps[:, :2], -40, 40)
    wps[:, 2] = np.clip(wps[:, 2], -4.0, -2.0)
    return {"id": "bench-1000", "frame": "ned", "start": "first_waypoint", "autostart": False,
            "waypoints": wps.round(3).tolist(),
            "bounds": {"velocity": 3, "acceleration": 3, "jerk": 10, "snap": 50}}


def flight_mission() -> dict[str, Any]:
    """A rectangle at 3 m (ENU), about 25 s at these bounds."""
    wps = [[0, 0, 3], [8, 0, 3], [8, 6, 3.5], [0, 6, 3.5], [0, 0, 3], [8, 0, 3], [8, 6, 3]]
    return {"id": "bench-flight", "frame": "enu", "start": "current", "waypoints": wps,
            "durations": [4.0] * (len(wps) - 1),
            "bounds": {"velocity": 4, "acceleration": 4, "jerk": 12, "snap": 60}}


def popup(i: int) -> dict[str, Any]:
    """A small box beside the rectangle's west edge (ENU x < -1.5): it changes the corridors but
    never blocks the path, so each one forces a replan that succeeds."""
    x0, y0 = -3.0 - 0.01 * i, 2.0 + 0.3 * i
    return {"frame": "enu", "add": [{"id": f"bench-popup-{i}",
                                     "A": [[1, 0, 0], [0, 1, 0], [0, 0, 1], [-1, 0, 0], [0, -1, 0], [0, 0, -1]],
                                     "b": [x0 + 1.0, y0 + 1.0, 5.0, -x0, -y0, -1.0]}]}


def _pct(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if len(values) else float("nan")


def run_rate(rate: float, flight: float, out: Path, popups: int, load: bool) -> dict[str, Any]:
    from companion.demo import rig

    out.mkdir(parents=True, exist_ok=True)
    mock_port, relay_port = _free_udp(), _free_udp()
    stamps_path = out / "setpoint_stamps.json"
    relay_proc = subprocess.Popen([sys.executable, __file__, "--relay", str(relay_port), str(mock_port),
                                   str(stamps_path)])
    result: dict[str, Any] = {"rate_hz": rate}
    try:
        with rig(out, "px4", rate_hz=rate, mav_port=mock_port, companion_mav_port=relay_port) as r:
            sampler = ProcSampler(r.companion.pid)
            t_put = r.peer.put("mission", flight_mission())
            t_stream = _wait_for_state(r.peer, "STREAMING", 40.0)
            sampler.start()
            cpu0, wall0 = sampler.cpu_seconds(), time.monotonic()
            plan_times: list[float] = []
            stop = threading.Event()
            loader = threading.Thread(target=_plan_load, args=(r.peer, stop, plan_times), daemon=True)
            if load:
                loader.start()
            popup_puts: list[float] = []
            traj_arrivals: list[float] = []
            for i in range(popups):
                _sleep_until(t_stream + 3.0 + i * (flight - 6.0) / max(popups, 1))
                n_before = _count_trajectories(r.peer)
                popup_puts.append(r.peer.put("obstacles", popup(i)))
                traj_arrivals.append(_wait_new_trajectory(r.peer, n_before, popup_puts[-1], 5.0))
            _sleep_until(t_stream + flight)
            cpu1, wall1 = sampler.cpu_seconds(), time.monotonic()
            stop.set()
            if load:
                loader.join(timeout=30)
            sampler.stop()
            result.update({
                "plan_first_trajectory_ms": 1e3 * (_first_traj_time(r.peer, t_put) - t_put),
                "cpu_percent": 100.0 * (cpu1 - cpu0) / (wall1 - wall0),
                "rss_max_mb": max(sampler.rss) if sampler.rss else float("nan"),
                "rss_peak_hwm_mb": sampler.peak_rss_mb(),
                "plans_1000_done": len(plan_times),
                "plan_1000_median_s": float(np.median(plan_times)) if plan_times else float("nan"),
                "window": (t_stream + 1.0, t_stream + flight),
            })
            window = result.pop("window")
    finally:
        relay_proc.send_signal(signal.SIGTERM)
        relay_proc.wait(10)
    stamps = np.asarray(json.loads(stamps_path.read_text()))
    inside = stamps[(stamps >= window[0]) & (stamps <= window[1])]
    jitter = np.abs(np.diff(inside) - 1.0 / rate) * 1e3
    result.update({"setpoints": len(inside), "jitter_p50_ms": _pct(jitter, 50),
                   "jitter_p99_ms": _pct(jitter, 99), "jitter_max_ms": float(jitter.max()) if len(jitter) else float("nan")})
    lat = []
    for put, arrived in zip(popup_puts, traj_arrivals, strict=True):
        after = stamps[stamps >= max(arrived, put)] if np.isfinite(arrived) else np.array([])
        lat.append(1e3 * (after[0] - put) if len(after) else float("nan"))
    result["popup_latencies_ms"] = [round(x, 2) for x in lat]
    result["latency_median_ms"] = float(np.nanmedian(lat)) if lat and np.isfinite(lat).any() else float("nan")
    return result


def _free_udp() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _sleep_until(t: float) -> None:
    delay = t - time.monotonic()
    if delay > 0:
        time.sleep(delay)


def _wait_for_state(peer: Any, state: str, timeout: float) -> float:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        st = peer.latest.get("status")
        if st is not None and isinstance(st.data, dict) and st.data.get("state") == state:
            return float(st.mono)
        time.sleep(0.01)
    raise RuntimeError(f"companion never reached {state} within {timeout:.0f} s")


def _count_trajectories(peer: Any) -> int:
    return len(peer.trajectory_log)


def _wait_new_trajectory(peer: Any, n_before: int, since: float, timeout: float) -> float:
    deadline = since + timeout
    while time.monotonic() < deadline:
        log = peer.trajectory_log
        if len(log) > n_before:
            return float(log[n_before])
        time.sleep(0.001)
    return float("nan")


def _first_traj_time(peer: Any, since: float) -> float:
    later = [t for t in peer.trajectory_log if t >= since]
    return later[0] if later else float("nan")


def _plan_load(peer: Any, stop: threading.Event, times: list[float]) -> None:
    mission = json.dumps(big_mission())
    while not stop.is_set():
        t0 = time.monotonic()
        replies = list(peer.session.get(f"{peer.base}/plan", payload=mission, timeout=60.0))
        if replies and replies[0].ok is not None:
            times.append(time.monotonic() - t0)
        elif replies:
            print(f"plan query failed: {replies[0].err.payload.to_string()[:200]}", file=sys.stderr)
            stop.wait(1.0)


def format_table(results: list[dict[str, Any]]) -> str:
    rows = [
        ("setpoints measured", "setpoints", "{:.0f}"),
        ("period jitter p50 [ms]", "jitter_p50_ms", "{:.3f}"),
        ("period jitter p99 [ms] (<= 2)", "jitter_p99_ms", "{:.3f}"),
        ("period jitter max [ms] (<= 10)", "jitter_max_ms", "{:.3f}"),
        ("pop-up -> new setpoint median [ms] (<= 20)", "latency_median_ms", "{:.1f}"),
        ("mission put -> trajectory [ms]", "plan_first_trajectory_ms", "{:.1f}"),
        ("1000-wp plans during flight", "plans_1000_done", "{:.0f}"),
        ("1000-wp plan, median [s]", "plan_1000_median_s", "{:.3f}"),
        ("companion RSS max [MB] (<= 150)", "rss_max_mb", "{:.1f}"),
        ("companion CPU [% of one core]", "cpu_percent", "{:.1f}"),
    ]
    head = ["", *[f"{r['rate_hz']:.0f} Hz" for r in results]]
    body = [[label, *[fmt.format(r.get(key, float("nan"))) for r in results]] for label, key, fmt in rows]
    widths = [max(len(row[i]) for row in [head, *body]) for i in range(len(head))]
    lines = [" | ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths, strict=True)))
             for row in [head, *body]]
    lines.insert(1, "-+-".join("-" * w for w in widths))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rates", type=float, nargs="+", default=[50.0, 100.0])
    p.add_argument("--flight", type=float, default=24.0, help="seconds of streaming measured per rate")
    p.add_argument("--popups", type=int, default=6)
    p.add_argument("--no-load", action="store_true", help="skip the parallel 1000-waypoint plans")
    p.add_argument("--out", type=Path, default=Path("out/bench/service"))
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--relay", nargs=3, metavar=("LISTEN", "TARGET", "OUT"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.relay:
        return relay(int(args.relay[0]), int(args.relay[1]), args.relay[2])
    results = []
    for rate in args.rates:
        print(f"flying {args.flight:.0f} s at {rate:.0f} Hz with {'1000-waypoint plans in parallel' if not args.no_load else 'no planning load'} ...",
              flush=True)
        results.append(run_rate(rate, args.flight, args.out / f"{rate:.0f}hz", args.popups, not args.no_load))
    print(format_table(results))
    at50 = next((r for r in results if r["rate_hz"] == 50.0), None)
    if at50 is not None:
        misses = [k for k, limit in TARGETS.items() if not at50.get(k, float("inf")) <= limit]
        print("targets at 50 Hz: " + ("all met" if not misses else "missed " + ", ".join(misses)))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"targets": TARGETS, "results": results}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
