"""Service benchmark: setpoint timing, pop-up-obstacle latency, memory and CPU of the companion.

Runs the real chain on loopback (mock autopilot, companion service, a Zenoh peer) at 50 Hz and
100 Hz. While the vehicle flies a mission, this script keeps the companion's planner busy with
1000-waypoint plan requests (the `plan` queryable) and publishes pop-up obstacles next to the path.

A small relay process sits on the MAVLink link (companion -> relay -> mock) and stamps every
SET_POSITION_TARGET_LOCAL_NED with CLOCK_MONOTONIC, which all processes on this machine share, so:
- setpoint jitter is |arrival interval - 1/rate| at the relay (it includes loopback and relay
  scheduling noise, so it overstates the companion's own jitter slightly), over the periodic
  stream: the companion also sends one setpoint at once when it swaps in a new plan, off the
  grid, and announces it (`latency` event with `sent_mono`, its CLOCK_MONOTONIC at the send);
  those are matched in the capture and left out of the period statistics;
- obstacle latency is from our `put` to the relay's arrival stamp of the first setpoint sampled
  from the replanned trajectory (the one the `latency` event announces).

Targets (at 50 Hz): jitter p99 <= 2 ms and max <= 10 ms, latency median <= 20 ms, RSS <= 150 MB
(the service process), every process of the companion together <= 300 MB while planning (PSS:
shared pages split among the processes that share them; benchmarks/footprint.py has idle too).
They are checked twice: with normal scheduling, and with the companion started under SCHED_FIFO
as the shipped systemd unit starts it (CPUSchedulingPolicy=fifo): the companion keeps that policy
for its setpoint thread only (companion/rtsched.py); everything else runs normally.

    python benchmarks/service.py [--rates 50 100] [--flight 24] [--json out/bench/service.json]
        [--nice -5]       # as the shipped systemd unit (Nice=-5)
        [--realtime 10]   # the realtime run's priority, as the unit's CPUSchedulingPriority=10
                          # (0: no realtime run)
        [--recording]     # also a 50 Hz run with the flight recorder on (its cost: jitter, CPU)
        [--recording-only]  # only the 50 Hz runs without and with the recorder
        [--aim]           # the companion aims with PX4 SIH's horizontal terms (setpoint sampling's cost)
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
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from planner_core.problem import Trajectory

MSG_SET_POSITION_TARGET_LOCAL_NED = 84
RELAY_PRIORITY = 20
TARGETS = {"jitter_p99_ms": 2.0, "jitter_max_ms": 10.0, "latency_median_ms": 20.0, "rss_max_mb": 150.0,
           "pss_tree_max_mb": 300.0}


# --- the relay (runs as its own process: `service.py --relay ...`) -----------------------------


def _msgid(packet: bytes) -> int | None:
    if len(packet) >= 10 and packet[0] == 0xFD:
        return int.from_bytes(packet[7:10], "little")
    if len(packet) >= 6 and packet[0] == 0xFE:
        return packet[5]
    return None


def relay(listen_port: int, target_port: int, out_path: str) -> int:
    """Forward UDP both ways; record the arrival time of every setpoint from the companion.

    The relay is the measuring instrument: where permitted it runs under SCHED_FIFO (above the
    companion's optional realtime priority), else at nice -10, so that on a busy computer its
    own scheduling delays do not show up as the companion's jitter."""
    try:
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(RELAY_PRIORITY))
    except (OSError, AttributeError):
        with contextlib.suppress(OSError):
            os.nice(-10)
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
            except TimeoutError:
                continue
            except OSError:  # e.g. ICMP port unreachable before the mock is up: never spin
                time.sleep(0.001)
                continue
            if peer:
                up.sendto(data, peer[0])

    threading.Thread(target=back, daemon=True).start()
    up.settimeout(0.2)
    while not stop.is_set():
        try:
            data, addr = up.recvfrom(65536)
        except TimeoutError:
            continue
        except OSError:
            time.sleep(0.001)
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


# --- the platform floor (its own process: `service.py --floor ...`) ----------------------------


def floor(rate: float, priority: int, nice: int, out_path: str) -> int:
    """A bare thread waking on the same absolute deadlines as the companion's setpoint thread,
    with the same scheduling, and doing nothing else: its wake-up times show what this computer
    (its other load, its timer interrupts; on a VM, the hypervisor) allows any sender."""
    stop = threading.Event()
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    wakes: list[float] = []

    def body() -> None:
        if priority > 0:
            with contextlib.suppress(OSError):
                os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
        elif nice:
            with contextlib.suppress(OSError):
                os.setpriority(os.PRIO_PROCESS, threading.get_native_id(), nice)
        t0, k = time.monotonic(), 0
        while not stop.is_set():
            k += 1
            delay = t0 + k / rate - time.monotonic()
            if delay > 0:
                time.sleep(delay)
            wakes.append(time.monotonic())

    worker = threading.Thread(target=body)
    worker.start()
    while worker.is_alive():
        worker.join(0.2)
    Path(out_path).write_text(json.dumps(wakes))
    return 0


# --- measurements ------------------------------------------------------------------------------


def _tree(pid: int) -> list[int]:
    """pid and its descendants (the companion may plan in worker processes)."""
    out, todo = [], [pid]
    while todo:
        p = todo.pop()
        out.append(p)
        with contextlib.suppress(OSError):
            for task in Path(f"/proc/{p}/task").iterdir():
                todo += [int(c) for c in (task / "children").read_text().split()]
    return out


def _status_kb(pid: int, field_name: str) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field_name + ":"):
            return float(line.split()[1])
    return 0.0


def _pss_kb(pid: int) -> float:
    with contextlib.suppress(OSError):
        for line in Path(f"/proc/{pid}/smaps_rollup").read_text().splitlines():
            if line.startswith("Pss:"):
                return float(line.split()[1])
    return 0.0


@dataclass
class ProcSampler:
    """RSS and CPU time of a process and its children, from /proc (Linux)."""

    pid: int
    rss: list[float] = field(default_factory=list)  # main process, MB
    rss_tree: list[float] = field(default_factory=list)  # with worker processes, MB
    pss_tree: list[float] = field(default_factory=list)  # the same in PSS (shared pages split), MB
    _stop: threading.Event = field(default_factory=threading.Event)
    _thread: threading.Thread | None = None

    def cpu_seconds(self) -> float:
        """User + system time of the process tree (children's time counts once they are reaped,
        so live workers are read one by one)."""
        total = 0.0
        for p in _tree(self.pid):
            with contextlib.suppress(OSError):
                fields = Path(f"/proc/{p}/stat").read_text().rsplit(")", 1)[1].split()
                total += int(fields[11]) + int(fields[12])
        return total / os.sysconf("SC_CLK_TCK")

    def start(self) -> None:
        def run() -> None:
            while not self._stop.wait(0.25):
                with contextlib.suppress(OSError):
                    self.rss.append(_status_kb(self.pid, "VmRSS") / 1024)
                    self.rss_tree.append(sum(_status_kb(p, "VmRSS") for p in _tree(self.pid)) / 1024)
                    self.pss_tree.append(sum(_pss_kb(p) for p in _tree(self.pid)) / 1024)

        self._thread = threading.Thread(target=run, daemon=True)
        self._thread.start()

    def stop(self) -> None:
        self._stop.set()
        if self._thread is not None:
            self._thread.join()


def big_mission(n: int = 1000, seed: int = 1) -> dict[str, Any]:
    """A 1000-waypoint random walk (NED, 2-4 m up, no obstacles) for the planner to chew on.

    Sent with autostart off while flying, the companion plans it in its planner thread (to check
    it) and keeps it pending: planning load without changing the flight.
    """
    rng = np.random.default_rng(seed)
    steps = rng.normal(size=(n - 1, 3)) * [2.0, 2.0, 0.3]
    # west of the flown rectangle (x north 0..6, y east 0..8), so no pop-up lands on it
    wps = np.cumsum(np.vstack([[-20.0, -30.0, -3.0], steps]), axis=0)
    wps[:, 0] = np.clip(wps[:, 0], -55.0, 55.0)
    wps[:, 1] = np.clip(wps[:, 1], -55.0, -12.0)
    wps[:, 2] = np.clip(wps[:, 2], -4.0, -2.0)
    return {"id": "bench-1000", "frame": "ned", "autostart": False, "waypoints": wps.round(3).tolist(),
            "bounds": {"velocity": 3, "acceleration": 3, "jerk": 10, "snap": 50}}


def flight_mission(laps: int = 2) -> dict[str, Any]:
    """Laps of a rectangle at 3 m (ENU). Its curve cuts the corners by up to ~2.5 m, which leaves
    room for pop-up obstacles that touch the curve without touching the straight legs."""
    lap = [[8, 0, 3], [8, 6, 3.5], [0, 6, 3.5], [0, 0, 3]]
    wps = [[0, 0, 3]] + lap * laps
    return {"id": "bench-flight", "frame": "enu", "waypoints": wps, "durations": [4.0] * (len(wps) - 1),
            "bounds": {"velocity": 4, "acceleration": 4, "jerk": 12, "snap": 60}}


def _leg_distance(points: np.ndarray, legs: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    out = np.full(len(points), np.inf)
    for a, b in legs:
        ab = b - a
        u = np.clip(((points - a) @ ab) / max(float(ab @ ab), 1e-12), 0.0, 1.0)
        out = np.minimum(out, np.linalg.norm(points - (a + u[:, None] * ab), axis=1))
    return out


def place_popup(traj: Trajectory, tau_now: float, i: int, window: tuple[float, float] = (3.0, 6.0),
                half: float = 0.1, push: float = 0.15) -> dict[str, Any] | None:
    """A small box (NED) just outside the curve 3-6 s ahead, where the curve is >= 1 m from the
    straight legs of the route still ahead (the trajectory's segment boundaries after now, and
    the chord from wherever the companion will split): the current trajectory enters it
    (inflated by the vehicle radius), so the companion must replan, and a corridor around it
    exists, so the replan can succeed. Nearer than ~3 s, the jet at the split point leaves no
    room to swerve and the companion brakes instead (checked offline: 9 of 15 replans succeed
    at 1-3 s, 20 of 22 at 3-6 s)."""
    taus = np.linspace(tau_now + window[0], min(tau_now + window[1], traj.t_end), 200)
    if taus[0] >= traj.t_end:
        return None
    pts = traj.evaluate(taus)
    ahead = traj.times[traj.times > tau_now + 0.15]
    route = traj.evaluate(ahead) if len(ahead) else traj.evaluate(np.array([traj.t_end]))
    splits = traj.evaluate(np.array([tau_now + 0.15, tau_now + 0.3, tau_now + 0.6]))
    legs = [(route[k], route[k + 1]) for k in range(len(route) - 1)] + [(p, route[0]) for p in splits]
    dist = _leg_distance(pts, legs)
    k = int(np.argmax(dist))
    if dist[k] < 1.0:
        return None
    nearest = min(legs, key=lambda leg: float(_leg_distance(pts[k:k + 1], [leg])[0]))
    ab = nearest[1] - nearest[0]
    foot = nearest[0] + np.clip(((pts[k] - nearest[0]) @ ab) / max(float(ab @ ab), 1e-12), 0, 1) * ab
    away = (pts[k] - foot) / max(float(np.linalg.norm(pts[k] - foot)), 1e-9)
    c = pts[k] + push * away
    eye = np.eye(3)
    return {"frame": "ned", "remove": [f"bench-popup-{i - 1}"] if i else [],
            "add": [{"id": f"bench-popup-{i}", "A": np.vstack([eye, -eye]).tolist(),
                     "b": np.concatenate([c + half, -(c - half)]).round(4).tolist()}]}


def _pct(values: np.ndarray, q: float) -> float:
    return float(np.percentile(values, q)) if len(values) else float("nan")


@dataclass
class Popup:
    put: float
    new_setpoint: float | None = None  # companion's send time of the first setpoint of the new plan
    companion_ms: float | None = None  # the companion's own message -> first setpoint
    event_arrival: float | None = None  # when its `latency` event reached us
    replanned: bool = False


def run_rate(rate: float, flight: float, out: Path, popups: int, load: bool,
             workers: int | None = None, realtime: int = 0, nice: int = 0, record: bool = False) -> dict[str, Any]:
    with started_under_fifo(realtime):
        return _run_rate(rate, flight, out, popups, load, workers, realtime, nice, record)


def _run_rate(rate: float, flight: float, out: Path, popups: int, load: bool,
              workers: int | None, realtime: int, nice: int, record: bool = False) -> dict[str, Any]:
    from demo.rig import rig

    out.mkdir(parents=True, exist_ok=True)
    mock_port, relay_port = _free_udp(), _free_udp()
    stamps_path = out / "setpoint_stamps.json"
    relay_proc = subprocess.Popen([sys.executable, __file__, "--relay", str(relay_port), str(mock_port),
                                   str(stamps_path)])
    floor_path = out / "floor_wakes.json"
    floor_proc: subprocess.Popen[bytes] | None = None
    result: dict[str, Any] = {"rate_hz": rate, "load": load, "workers": workers or 1, "realtime": realtime,
                              "recording": record}
    mission = flight_mission()
    results: list[Popup] = []
    try:
        with rig(out, "px4", rate_hz=rate, mav_port=mock_port, companion_mav_port=relay_port,
                 workers=workers, recording=out / "recordings" if record else None, settings=SETTINGS) as r:
            events = _EventLog(r.peer)
            t_put = r.peer.put("mission", mission)
            events.wait(lambda e: e.get("type") == "accepted" and e.get("key") == "mission", t_put, 20.0)
            r.peer.put("command", {"command": "start"})
            t_stream = events.wait(lambda e: e.get("type") == "state" and e.get("to") == "STREAMING", t_put, 60.0)
            if t_stream is None:
                raise RuntimeError("the companion never started streaming the mission\n" + r.companion.tail())
            if nice:
                result["niced_threads"] = renice_tree(r.companion.pid, nice)
            result["setpoint_thread"] = setpoint_thread_scheduling(r.companion.pid)
            result["realtime_threads"] = realtime_threads(r.companion.pid)
            floor_proc = subprocess.Popen([sys.executable, __file__, "--floor", str(rate), str(realtime),
                                           str(nice), str(floor_path)])
            sampler = ProcSampler(r.companion.pid)
            sampler.start()
            cpu0, wall0 = sampler.cpu_seconds(), time.monotonic()
            plan_times: list[float] = []
            stop = threading.Event()
            loader = threading.Thread(target=_plan_load, args=(r.peer, events, stop, plan_times), daemon=True)
            if load:
                loader.start()
            # the mission starts with a slow rest-to-rest climb from the takeoff point: no curve
            # to put an obstacle beside before ~7 s
            for i in range(popups):
                _sleep_until(t_stream + 7.0 + i * (flight - 9.0) / max(popups, 1))
                results.append(_one_popup(r.peer, events, i))
            _sleep_until(t_stream + flight)
            cpu1, wall1 = sampler.cpu_seconds(), time.monotonic()
            # the companion's own view: periods between its sends (its clock, no relay or
            # loopback in between), over its last 1000 setpoints
            own = (r.peer.query("status", timeout=2.0) or {}).get("setpoint_period_ms") or {}
            result["own_period_p99_ms"] = own.get("p99", float("nan"))
            result["own_period_max_ms"] = own.get("max", float("nan"))
            stop.set()
            if load:
                loader.join(timeout=60)
            sampler.stop()
            result.update({
                "cpu_percent": 100.0 * (cpu1 - cpu0) / (wall1 - wall0),
                "rss_max_mb": max(sampler.rss) if sampler.rss else float("nan"),
                "rss_tree_max_mb": max(sampler.rss_tree) if sampler.rss_tree else float("nan"),
                "pss_tree_max_mb": max(sampler.pss_tree) if sampler.pss_tree else float("nan"),
                "processes": len(_tree(r.companion.pid)),
                "plans_1000_done": len(plan_times),
                "plan_1000_median_s": float(np.median(plan_times)) if plan_times else float("nan"),
            })
            window = (t_stream + 1.0, t_stream + flight)
            time.sleep(0.5)  # the last events
            with events._lock:
                immediate = [float(ev["sent_mono"]) for _, ev in events.items
                             if ev.get("type") == "latency" and ev.get("immediate") and "sent_mono" in ev]
    finally:
        for proc in (relay_proc, floor_proc):
            if proc is not None:
                proc.send_signal(signal.SIGTERM)
                proc.wait(10)
    stamps = np.asarray(json.loads(stamps_path.read_text()))
    wakes = np.asarray(json.loads(floor_path.read_text()))
    wakes = wakes[(wakes >= window[0]) & (wakes <= window[1])]
    floor_jitter = np.abs(np.diff(wakes) - 1.0 / rate) * 1e3
    result.update({"floor_jitter_p99_ms": _pct(floor_jitter, 99),
                   "floor_jitter_max_ms": float(floor_jitter.max()) if len(floor_jitter) else float("nan")})
    extra = off_grid(stamps, immediate)
    periodic = np.delete(stamps, extra)
    inside = periodic[(periodic >= window[0]) & (periodic <= window[1])]
    result["immediate_setpoints"] = len(extra)
    jitter = np.abs(np.diff(inside) - 1.0 / rate) * 1e3
    result.update({"setpoints": len(inside), "jitter_p50_ms": _pct(jitter, 50),
                   "jitter_p99_ms": _pct(jitter, 99),
                   "jitter_max_ms": float(jitter.max()) if len(jitter) else float("nan")})
    lat = []
    for p in results:
        if p.new_setpoint is None and p.event_arrival is not None:
            # a companion that does not stamp its sends (older versions): the setpoint is the
            # last one the relay forwarded before the `latency` event reached us
            before = stamps[stamps <= p.event_arrival]
            lat.append(1e3 * (before[-1] - p.put) if len(before) and before[-1] >= p.put else float("nan"))
            continue
        if p.new_setpoint is None:
            lat.append(float("nan"))
            continue
        # the relay's stamp of that setpoint: the first one it forwarded after the companion sent it
        k = int(np.searchsorted(stamps, p.new_setpoint))
        ok_k = k < len(stamps) and stamps[k] - p.new_setpoint <= MATCH_S
        lat.append(1e3 * (stamps[k] - p.put) if ok_k else float("nan"))
    ok = np.isfinite(lat)
    result["popups_replanned"] = f"{int(sum(p.replanned for p in results))}/{len(results)}"
    result["popup_latencies_ms"] = [round(x, 2) for x in lat]
    result["latency_median_ms"] = float(np.median(np.asarray(lat)[ok])) if ok.any() else float("nan")
    inner = [p.companion_ms for p in results if p.companion_ms is not None]
    result["companion_latency_median_ms"] = float(np.median(inner)) if inner else float("nan")
    return result


# --- the loaded computer (issue 21): missions every 1.5 s beside a CPU hog, and a memory soak ----


def small_mission(i: int, rng: np.random.Generator) -> dict[str, Any]:
    """A valid 5-waypoint mission near the flown rectangle (ENU, 2.5-4 m up), new each time."""
    base = np.array([4.0, 3.0, 3.2])
    wps = base + rng.uniform([-3.0, -3.0, -0.6], [3.0, 3.0, 0.6], size=(5, 3))
    return {"id": f"loaded-{i}", "frame": "enu", "waypoints": wps.round(2).tolist()}


# --aim: the companion's config changes ([setpoints] aim_horizontal: PX4 SIH's terms, the most a
# setpoint tick samples), for every rig this run starts
SETTINGS: list[str] = []


def _hog() -> subprocess.Popen[bytes]:
    """A process spinning on a core, under normal scheduling, as another job on the computer."""
    return subprocess.Popen([sys.executable, "-c", "while True: pass"])


@contextlib.contextmanager
def relayed_flight(out: Path, hog: bool, laps: int, search_time: float | None = None) -> Iterator[tuple[Any, Any, Path]]:
    """A PX4-flavour rig with the stamping relay on its MAVLink link (and a CPU hog beside it if
    asked), flying `laps` of the rectangle: (rig, its event log, where the relay writes its
    stamps once this closes)."""
    from demo.rig import rig

    out.mkdir(parents=True, exist_ok=True)
    mock_port, relay_port = _free_udp(), _free_udp()
    stamps_path = out / "setpoint_stamps.json"
    relay_proc = subprocess.Popen([sys.executable, __file__, "--relay", str(relay_port), str(mock_port),
                                   str(stamps_path)])
    hog_proc = _hog() if hog else None
    try:
        with rig(out, "px4", mav_port=mock_port, companion_mav_port=relay_port, search_time=search_time,
                 settings=SETTINGS) as r:
            events = _EventLog(r.peer)
            t_put = r.peer.put("mission", flight_mission(laps=laps))
            events.wait(lambda e: e.get("type") == "accepted" and e.get("key") == "mission", t_put, 30.0)
            r.peer.put("command", {"command": "start"})
            if events.wait(lambda e: e.get("type") == "state" and e.get("to") == "STREAMING", t_put, 90.0) is None:
                raise RuntimeError("the companion never started streaming\n" + r.companion.tail())
            time.sleep(2.0)
            yield r, events, stamps_path
    finally:
        for proc in (relay_proc, hog_proc):
            if proc is not None:
                proc.send_signal(signal.SIGTERM)
                proc.wait(10)


def run_loaded(out: Path, every: float, duration: float, soak: int, hog: bool) -> dict[str, Any]:
    """Fly; send a valid 5-waypoint mission every `every` s for `duration` s (each replaces the
    one flying); then `soak` 1000-waypoint missions (checked, kept pending, each replacing the
    last) and obstacle additions and removals, then one small pending mission: the companion's
    main and tree RSS before and after. Setpoint gaps at the relay over the mission phase."""
    result: dict[str, Any] = {"hog": hog, "every_s": every, "duration_s": duration, "aim": bool(SETTINGS)}
    rng = np.random.default_rng(7)
    with relayed_flight(out, hog, 20) as (r, events, stamps_path):
        pid = r.companion.pid
        result["rss_idle_mb"] = _status_kb(pid, "VmRSS") / 1024
        result["rss_tree_idle_mb"] = sum(_status_kb(p, "VmRSS") for p in _tree(pid)) / 1024
        sent, answers = 0, {}
        t0 = time.monotonic()
        while time.monotonic() - t0 < duration:
            m = small_mission(sent, rng)
            put = r.peer.put("mission", m)
            sent += 1
            mid = m["id"]
            answers[mid] = (put, None)
            _sleep_until(put + every)
        t1 = time.monotonic()
        time.sleep(3.0)  # the last answers
        with events._lock:
            for _, ev in events.items:
                mid = ev.get("mission")
                if mid in answers and ev.get("key") == "mission" and ev.get("type") in ("accepted", "rejected"):
                    answers[mid] = (answers[mid][0], ev)
        accepted = [a for a in answers.values() if a[1] is not None and a[1]["type"] == "accepted"]
        rejected = [a[1] for a in answers.values() if a[1] is not None and a[1]["type"] == "rejected"]
        result.update({"missions_sent": sent, "missions_accepted": len(accepted),
                       "missions_rejected": len(rejected),
                       "rejections": sorted({str(e.get("reason", ""))[:120] for e in rejected}),
                       "stalled_events": sum(1 for _, ev in list(events.items) if ev.get("type") == "stalled")})
        window = (t0 + 0.5, t1)
        for i in range(soak):
            big = big_mission(1000, seed=100 + i)
            t = r.peer.put("mission", big)
            events.wait(lambda e: e.get("key") == "mission" and e.get("type") in ("accepted", "rejected"), t, 120.0)
            ids = [f"soak-{i}-{k}" for k in range(50)]
            r.peer.put("obstacles", {"add": [{"id": n, "vertices": [[-40.0 + k, -40.0 + dx, -3.0 + dz] for dx in (0, 1)
                                                                    for dz in (0, 1) for k in (0, 1)]}
                                             for n in ids]})
            time.sleep(0.5)
            r.peer.put("obstacles", {"remove": ids})
        last = small_mission(9999, rng) | {"autostart": False}
        t = r.peer.put("mission", last)
        events.wait(lambda e: e.get("key") == "mission" and e.get("type") in ("accepted", "rejected"), t, 30.0)
        time.sleep(5.0)
        result["rss_after_soak_mb"] = _status_kb(pid, "VmRSS") / 1024
        result["rss_tree_after_soak_mb"] = sum(_status_kb(p, "VmRSS") for p in _tree(pid)) / 1024
        result["soak_missions"] = soak
    stamps = np.asarray(json.loads(stamps_path.read_text()))
    inside = stamps[(stamps >= window[0]) & (stamps <= window[1])]
    gaps = np.diff(inside) * 1e3
    result.update({"setpoints": len(inside), "gap_p99_ms": _pct(gaps, 99),
                   "gap_max_ms": float(gaps.max()) if len(gaps) else float("nan")})
    return result


def sized_mission(mid: str, n: int, rng: np.random.Generator) -> dict[str, Any]:
    """A valid n-waypoint mission (ENU, 2.5-4 m up) starting near the flown rectangle: a random walk
    of 1.5 m steps kept inside a 60 m square, new each time."""
    steps = rng.normal(size=(n - 1, 3)) * [1.5, 1.5, 0.2]
    wps = np.cumsum(np.vstack([[4.0, 3.0, 3.2], steps]), axis=0)
    wps[:, :2] = np.clip(wps[:, :2], -30.0, 30.0)
    wps[:, 2] = np.clip(wps[:, 2], 2.5, 4.0)
    return {"id": mid, "frame": "enu", "waypoints": wps.round(2).tolist()}


PUT_TARGETS = {"put_5_median_ms": 30.0, "put_100_median_ms": 60.0, "put_1000_median_ms": 200.0}


def run_put(out: Path, sizes: list[int], each: int, hog: bool, search_time: float | None = None) -> dict[str, Any]:
    """Issue 25.1: while the vehicle flies, missions of each size (no durations: the fastest
    allocation, as the companion plans by default), one after the other, each replacing the one
    flying: from our put to the relay's arrival stamp of the first setpoint of the new plan (the
    one the `latency` event announces), and the flight time each was planned for."""
    rng = np.random.default_rng(11)
    samples: list[dict[str, Any]] = []
    with relayed_flight(out, hog, 40, search_time) as (r, events, stamps_path):
        for n in sizes:
            for k in range(each):
                mid = f"put-{n}-{k}"
                put = r.peer.put("mission", sized_mission(mid, n, rng))
                done = events.wait(lambda e, mid=mid: e.get("mission") == mid and e.get("key") == "mission"
                                   and e.get("type") in ("accepted", "rejected"), put, 120.0)
                what = f"mission {mid}"
                events.wait(lambda e, what=what: e.get("type") == "latency" and e.get("what") == what, put, 2.0)
                # the anytime start's search ([planner] anytime): the next put waits for it, as it
                # would queue behind it in the planner process
                events.wait(lambda e, mid=mid: e.get("type") == "improved" and e.get("mission") == mid, put, 6.0)
                with events._lock:
                    evs = [ev for m, ev in events.items if m >= put]
                answer = next((e for e in evs if e.get("mission") == mid and e.get("key") == "mission"
                               and e.get("type") in ("accepted", "rejected")), None)
                lat = next((e for e in evs if e.get("type") == "latency" and e.get("what") == what), None)
                better = next((e for e in evs if e.get("type") == "improved" and e.get("mission") == mid), None)
                samples.append({"n": n, "put": put, "answered": done is not None,
                                "improved_s": None if better is None else better.get("earlier_s"),
                                "accepted": answer is not None and answer["type"] == "accepted",
                                "message": None if answer is None else str(answer.get("message", ""))[:200],
                                "sent_mono": None if lat is None else lat.get("sent_mono"),
                                "companion_ms": None if lat is None else lat.get("latency_ms"),
                                "plan_ms": None if answer is None else answer.get("plan_ms"),
                                "compute_ms": None if answer is None else answer.get("compute_ms")})
                time.sleep(1.0)
    stamps = np.asarray(json.loads(stamps_path.read_text()))
    result: dict[str, Any] = {"hog": hog, "each": each, "search_time": search_time, "samples": samples}
    for n in sizes:
        rows = [x for x in samples if x["n"] == n]
        put_ms = []
        for x in rows:
            if x["sent_mono"] is None:
                continue
            k = off_grid(stamps, [float(x["sent_mono"])])
            if k:
                put_ms.append((float(stamps[k[0]]) - x["put"]) * 1e3)
        comp = [float(x["companion_ms"]) for x in rows if x["companion_ms"] is not None]
        plan = [float(x["plan_ms"]) for x in rows if x.get("plan_ms") is not None]
        compute = [float(x["compute_ms"]) for x in rows if x.get("compute_ms") is not None]
        capped = [x for x in rows if x["message"] and "stopped after" in x["message"]]
        result.update({f"put_{n}_median_ms": float(np.median(put_ms)) if put_ms else float("nan"),
                       f"put_{n}_max_ms": float(np.max(put_ms)) if put_ms else float("nan"),
                       f"companion_{n}_median_ms": float(np.median(comp)) if comp else float("nan"),
                       f"plan_{n}_median_ms": float(np.median(plan)) if plan else float("nan"),
                       f"compute_{n}_median_ms": float(np.median(compute)) if compute else float("nan"),
                       f"accepted_{n}": sum(1 for x in rows if x["accepted"]), f"sent_{n}": len(rows),
                       f"capped_{n}": len(capped),
                       f"improved_{n}": sum(1 for x in rows if x["improved_s"] is not None),
                       f"improved_{n}_median_s": float(np.median([x["improved_s"] for x in rows
                                                                  if x["improved_s"] is not None] or [np.nan]))})
    return result


def format_put(results: list[dict[str, Any]], sizes: list[int]) -> str:
    head = ["", *["CPU hog" if r["hog"] else "quiet" for r in results]]
    body = []
    for n in sizes:
        target = PUT_TARGETS.get(f"put_{n}_median_ms")
        body += [[f"{n} waypoints: put -> first setpoint of the new plan, median [ms]"
                  + (f" (<= {target:g})" if target else ""), *[f"{r[f'put_{n}_median_ms']:.1f}" for r in results]],
                 ["  max [ms]", *[f"{r[f'put_{n}_max_ms']:.1f}" for r in results]],
                 ["  companion's own clock (arrival -> send), median [ms]",
                  *[f"{r[f'companion_{n}_median_ms']:.1f}" for r in results]],
                 ["    of which the plan's round trip to the planner process / the planner's own time [ms]",
                  *[f"{r.get(f'plan_{n}_median_ms', float('nan')):.1f} / {r.get(f'compute_{n}_median_ms', float('nan')):.1f}"
                    for r in results]],
                 ["  accepted / sent; search cut to fit", *[f"{r[f'accepted_{n}']} / {r[f'sent_{n}']}; {r[f'capped_{n}']}"
                                                             for r in results]],
                 ["  the fastest durations swapped in later (anytime start); median s earlier",
                  *[f"{r[f'improved_{n}']}; {r[f'improved_{n}_median_s']:.2f}" for r in results]]]
    return grid(head, body)


LOADED_TARGETS = {"gap_max_ms": 60.0, "missions_flown_percent": 100.0, "rss_regrowth_mb": 10.0}


def format_loaded(r: dict[str, Any]) -> str:
    flown = 100.0 * r["missions_accepted"] / max(r["missions_sent"], 1)
    regrowth = r["rss_after_soak_mb"] - r["rss_idle_mb"]
    rows = [
        ["setpoints measured", f"{r['setpoints']}", ""],
        ["setpoint gap p99 (ms)", f"{r['gap_p99_ms']:.1f}", ""],
        ["setpoint gap max (ms)", f"{r['gap_max_ms']:.1f}", f"<= {LOADED_TARGETS['gap_max_ms']:.0f}"],
        [f"missions accepted / sent (1 per {r['every_s']} s)", f"{r['missions_accepted']} / {r['missions_sent']}",
         "all"],
        ["stalled events", f"{r['stalled_events']}", "0"],
        ["main RSS idle -> after soak (MB)", f"{r['rss_idle_mb']:.0f} -> {r['rss_after_soak_mb']:.0f}",
         f"within {LOADED_TARGETS['rss_regrowth_mb']:.0f}"],
        ["tree RSS idle -> after soak (MB)", f"{r['rss_tree_idle_mb']:.0f} -> {r['rss_tree_after_soak_mb']:.0f}", ""],
    ]
    text = grid(["loaded computer" + (" (CPU hog beside)" if r["hog"] else "") + (", aim" if r.get("aim") else ""),
                 "measured", "target"], rows)
    if r["rejections"]:
        text += "\nrejections: " + "; ".join(r["rejections"])
    r["missions_flown_percent"], r["rss_regrowth_mb"] = flown, regrowth
    return text


class _EventLog:
    """Every event with its arrival time, kept apart from the demo peer's queue."""

    def __init__(self, peer: Any) -> None:
        self.items: list[tuple[float, dict[str, Any]]] = []
        self._lock = threading.Lock()
        self._sub = peer.session.declare_subscriber(f"{peer.base}/events", self._on)

    def _on(self, sample: Any) -> None:
        mono = time.monotonic()
        with contextlib.suppress(ValueError):
            ev = json.loads(sample.payload.to_bytes())
            with self._lock:
                self.items.append((mono, ev))

    def wait(self, pred: Any, since: float, timeout: float) -> float | None:
        deadline = time.monotonic() + timeout
        seen = 0
        while time.monotonic() < deadline:
            with self._lock:
                items = list(self.items)
            for mono, ev in items[seen:]:
                if mono >= since and pred(ev):
                    return mono
            seen = len(items)
            time.sleep(0.002)
        return None


def _one_popup(peer: Any, events: _EventLog, i: int) -> Popup:
    from demo.analysis import trajectory_of

    latest = peer.latest.get("trajectory")
    status = peer.query("status", timeout=1.0) or {}
    if latest is None:
        return Popup(put=time.monotonic())
    traj = trajectory_of(latest)
    # trajectory time now: the status says how far along the route we are
    tau_now = traj.t_end - float(status.get("time_to_go") or 0.0)
    msg = place_popup(traj, tau_now, i)
    if msg is None:
        return Popup(put=time.monotonic())
    p = Popup(put=peer.put("obstacles", msg))
    hit = events.wait(lambda e: e.get("type") in ("replanned", "obstacles_clear", "braking"), p.put, 10.0)
    if hit is None:
        return p
    mono_ev = events.wait(lambda e: e.get("type") == "latency", p.put, 2.0)
    with events._lock:
        kinds = [ev.get("type") for m, ev in events.items if m >= p.put]
        lat = [ev for m, ev in events.items if m >= p.put and ev.get("type") == "latency"]
    p.replanned = "replanned" in kinds
    if mono_ev is not None and lat and p.replanned:
        p.new_setpoint = float(lat[0]["sent_mono"]) if "sent_mono" in lat[0] else None
        p.event_arrival = mono_ev
        p.companion_ms = float(lat[0].get("latency_ms", float("nan")))
    return p


MATCH_S = 0.005  # a setpoint reaches the relay within this of its send (loopback)


def off_grid(stamps: np.ndarray, sent: list[float]) -> list[int]:
    """Indices of the relay stamps of the setpoints sent at `sent` (companion clock, same
    CLOCK_MONOTONIC): for each, the first stamp at or after it, if within MATCH_S."""
    out = []
    for t in sent:
        k = int(np.searchsorted(stamps, t))
        if k < len(stamps) and stamps[k] - t <= MATCH_S:
            out.append(k)
    return sorted(set(out))


def renice_tree(pid: int, increment: int) -> int:
    """What systemd's `Nice=` does to the service, applied from outside: every thread of the
    companion and of its planner processes, niced by `increment` from where it is (the planner
    processes keep their own offset). Returns the threads changed."""
    changed = 0
    for p in _tree(pid):
        with contextlib.suppress(OSError):
            for task in Path(f"/proc/{p}/task").iterdir():
                tid = int(task.name)
                with contextlib.suppress(OSError):
                    now = os.getpriority(os.PRIO_PROCESS, tid)
                    os.setpriority(os.PRIO_PROCESS, tid, max(-20, min(19, now + increment)))
                    changed += 1
    return changed


@contextlib.contextmanager
def started_under_fifo(priority: int) -> Iterator[None]:
    """While active, the rig starts the companion as systemd does with CPUSchedulingPolicy=fifo
    and CPUSchedulingPriority=`priority` (> 0): under SCHED_FIFO from its first instruction
    (`chrt` execs it). Raises if this machine does not permit it."""
    if priority <= 0:
        yield
        return
    if subprocess.run(["chrt", "-f", str(priority), "true"], capture_output=True).returncode != 0:
        raise RuntimeError(f"SCHED_FIFO {priority} is not permitted here (needs CAP_SYS_NICE); "
                           "run with --realtime 0")
    from demo import rig as demo_rig

    original = demo_rig.Child.__init__

    def init(self: Any, name: str, argv: list[str], log: Path) -> None:
        original(self, name, ["chrt", "-f", str(priority), *argv] if name == "companion" else argv, log)

    demo_rig.Child.__init__ = init  # type: ignore[method-assign]
    try:
        yield
    finally:
        demo_rig.Child.__init__ = original  # type: ignore[method-assign]


def _policy(tid: int) -> str:
    try:
        policy = os.sched_getscheduler(tid)
        prio = os.sched_getparam(tid).sched_priority
    except OSError:
        return "?"
    return {os.SCHED_FIFO: f"fifo {prio}", os.SCHED_RR: f"rr {prio}"}.get(policy, "normal")


def setpoint_thread_scheduling(pid: int) -> str:
    """How the companion's setpoint thread (named `setpoints`) is scheduled."""
    for task in Path(f"/proc/{pid}/task").iterdir():
        with contextlib.suppress(OSError):
            if (task / "comm").read_text().strip() == "setpoints":
                return _policy(int(task.name))
    return "not found"


def realtime_threads(pid: int) -> int:
    """Threads of the companion and its planner processes under a realtime policy: the
    setpoint thread should be the only one."""
    n = 0
    for p in _tree(pid):
        with contextlib.suppress(OSError):
            for task in Path(f"/proc/{p}/task").iterdir():
                n += _policy(int(task.name)) not in ("normal", "?")
    return n


def _free_udp() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _sleep_until(t: float) -> None:
    delay = t - time.monotonic()
    if delay > 0:
        time.sleep(delay)


def _plan_load(peer: Any, events: _EventLog, stop: threading.Event, times: list[float]) -> None:
    mission = big_mission()
    while not stop.is_set():
        t0 = peer.put("mission", mission)
        done = events.wait(lambda e: e.get("key") == "mission" and e.get("type") in ("accepted", "rejected")
                           and "bench-1000" in str(e.get("message", "")), t0, 60.0)
        if done is None:
            return
        times.append(done - t0)


def column(r: dict[str, Any]) -> str:
    return (f"{r['rate_hz']:.0f} Hz" + ("" if r.get("load", True) else ", no load")
            + (f", fifo {r['realtime']}" if r.get("realtime") else "") + (", recording" if r.get("recording") else ""))


def format_table(results: list[dict[str, Any]]) -> str:
    rows = [
        ("setpoints measured (periodic)", "setpoints", "{:.0f}"),
        ("  immediate setpoints on a swap (left out)", "immediate_setpoints", "{:.0f}"),
        ("setpoint thread scheduling", "setpoint_thread", "{}"),
        ("  threads under a realtime policy (all processes)", "realtime_threads", "{}"),
        ("period jitter p50 [ms]", "jitter_p50_ms", "{:.3f}"),
        ("period jitter p99 [ms] (<= 2)", "jitter_p99_ms", "{:.3f}"),
        ("period jitter max [ms] (<= 10)", "jitter_max_ms", "{:.3f}"),
        ("  companion's own send period p99 [ms]", "own_period_p99_ms", "{:.3f}"),
        ("  companion's own send period max [ms]", "own_period_max_ms", "{:.3f}"),
        ("  platform floor: a bare thread's period jitter p99 [ms]", "floor_jitter_p99_ms", "{:.3f}"),
        ("  platform floor: same, max [ms]", "floor_jitter_max_ms", "{:.3f}"),
        ("pop-ups that forced a replan", "popups_replanned", "{}"),
        ("pop-up put -> new setpoint, median [ms] (<= 20)", "latency_median_ms", "{:.1f}"),
        ("  same, companion's own clock [ms]", "companion_latency_median_ms", "{:.1f}"),
        ("1000-wp plans during flight", "plans_1000_done", "{:.0f}"),
        ("1000-wp plan, median [s]", "plan_1000_median_s", "{:.3f}"),
        ("companion RSS max [MB] (<= 150)", "rss_max_mb", "{:.1f}"),
        ("  with planner worker processes [MB]", "rss_tree_max_mb", "{:.1f}"),
        ("  same, PSS [MB] (<= 300)", "pss_tree_max_mb", "{:.1f}"),
        ("companion CPU, all processes [% of one core]", "cpu_percent", "{:.1f}"),
    ]
    head = ["", *[column(r) for r in results]]
    body = [[label, *[fmt.format(r.get(key, float("nan"))) for r in results]] for label, key, fmt in rows]
    return grid(head, body)


def grid(head: list[str], body: list[list[str]]) -> str:
    """Cells as a text table: the first column left-aligned, the others right-aligned, a rule
    under the head."""
    widths = [max(len(row[i]) for row in [head, *body]) for i in range(len(head))]
    lines = [" | ".join(c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths, strict=True)))
             for row in [head, *body]]
    lines.insert(1, "-+-".join("-" * w for w in widths))
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--rates", type=float, nargs="+", default=[50.0, 100.0])
    p.add_argument("--flight", type=float, default=30.0, help="seconds of streaming measured per rate")
    p.add_argument("--popups", type=int, default=6)
    p.add_argument("--no-load", action="store_true", help="skip the parallel 1000-waypoint plans")
    p.add_argument("--no-baseline", action="store_true", help="skip the 50 Hz run without planning load")
    p.add_argument("--workers", type=int, default=None, help="companion planner threads (default: its own)")
    p.add_argument("--nice", type=int, default=0, metavar="N",
                   help="renice the companion and its planner processes by N, as systemd's Nice= does "
                   "(the shipped unit has Nice=-5)")
    p.add_argument("--realtime", type=int, default=10, metavar="PRIO",
                   help="also fly 50 Hz with planning load with the companion started under SCHED_FIFO "
                   "PRIO, as the systemd unit starts it (CPUSchedulingPolicy=fifo, CPUSchedulingPriority=10); "
                   "0: skip that run")
    p.add_argument("--realtime-only", action="store_true", help="only the realtime run")
    p.add_argument("--recording", action="store_true",
                   help="also fly 50 Hz with planning load with the flight recorder on ([recording] path): its cost")
    p.add_argument("--aim", action="store_true",
                   help="the companion aims with PX4 SIH's horizontal terms ([setpoints] aim_horizontal; the most "
                   "a setpoint tick samples): their cost on the stream")
    p.add_argument("--recording-only", action="store_true",
                   help="only the 50 Hz runs with planning load without and with the recorder")
    p.add_argument("--out", type=Path, default=Path("out/bench/service"))
    p.add_argument("--json", type=Path, default=None)
    p.add_argument("--loaded", action="store_true",
                   help="only the loaded-computer run (issue 21): missions every --every s for --duration s "
                   "beside a CPU hog (--no-hog: without), then a memory soak of --soak big missions")
    p.add_argument("--every", type=float, default=1.5)
    p.add_argument("--duration", type=float, default=20.0)
    p.add_argument("--soak", type=int, default=6)
    p.add_argument("--no-hog", action="store_true")
    p.add_argument("--put", action="store_true",
                   help="only mission put -> first setpoint of the new plan in flight (issue 25.1), for "
                   "--sizes waypoints, --each missions of each size, quiet and beside a CPU hog (--no-hog: quiet only)")
    p.add_argument("--sizes", type=int, nargs="+", default=[5, 100, 1000])
    p.add_argument("--each", type=int, default=5)
    p.add_argument("--search-time", type=float, default=None, help="the companion's [planner] search_time (s)")
    p.add_argument("--relay", nargs=3, metavar=("LISTEN", "TARGET", "OUT"), help=argparse.SUPPRESS)
    p.add_argument("--floor", nargs=4, metavar=("RATE", "PRIO", "NICE", "OUT"), help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.aim:
        from companion.lag import PX4_SIH_AIM_HORIZONTAL

        SETTINGS.append(f"setpoints.aim_horizontal={[list(t) for t in PX4_SIH_AIM_HORIZONTAL]}")
    if args.relay:
        return relay(int(args.relay[0]), int(args.relay[1]), args.relay[2])
    if args.floor:
        return floor(float(args.floor[0]), int(args.floor[1]), int(args.floor[2]), args.floor[3])
    if args.put:
        put_runs = [run_put(args.out / ("put-hog" if hog else "put"), args.sizes, args.each, hog, args.search_time)
                    for hog in ([False] if args.no_hog else [False, True])]
        print(format_put(put_runs, args.sizes))
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps({"targets": PUT_TARGETS, "put": put_runs}, indent=2))
        return 0
    if args.loaded:
        res = run_loaded(args.out / "loaded", args.every, args.duration, args.soak, not args.no_hog)
        print(format_loaded(res))
        if args.json:
            args.json.parent.mkdir(parents=True, exist_ok=True)
            args.json.write_text(json.dumps({"targets": LOADED_TARGETS, "loaded": res}, indent=2))
        return 0
    runs = [] if args.realtime_only else [(rate, not args.no_load, 0, False) for rate in args.rates]
    if not args.no_baseline and not args.no_load and not args.realtime_only:
        runs.append((50.0, False, 0, False))
    if args.realtime > 0:
        runs.append((50.0, not args.no_load, args.realtime, False))
    if args.recording:
        runs.append((50.0, not args.no_load, 0, True))
    if args.recording_only:
        runs = [(50.0, not args.no_load, 0, False), (50.0, not args.no_load, 0, True)]
    results = []
    for rate, load, prio, record in runs:
        what = "1000-waypoint plans in parallel" if load else "no planning load"
        how = (f", started under SCHED_FIFO {prio} (as the systemd unit)" if prio else "") + (
            ", flight recorder on" if record else "")
        print(f"flying {args.flight:.0f} s at {rate:.0f} Hz with {what}{how} ...", flush=True)
        tag = f"{rate:.0f}hz" + ("" if load else "-noload") + (f"-fifo{prio}" if prio else "") + ("-rec" if record else "")
        results.append(run_rate(rate, args.flight, args.out / tag, args.popups, load, args.workers,
                                prio, args.nice, record))
    print(format_table(results))
    for r in results:
        if r["rate_hz"] == 50.0 and r.get("load", True):
            misses = [k for k, limit in TARGETS.items() if not r.get(k, float("inf")) <= limit]
            print(f"targets at {column(r)}: " + ("all met" if not misses else "missed " + ", ".join(misses)))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"targets": TARGETS, "results": results}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
