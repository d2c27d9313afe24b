"""The fleet demo (issue 24.5): `python -m demo --fleet 3` (`make demo-fleet`).

One Zenoh router (`python -m companion router`, loopback), N `sitl_mock --home` on a circle of
10 m about the fleet origin, N companions joining the router as clients with `[fleet] origin` and
`separation`. Each vehicle takes off, then all are sent, at the same instant, a crossing mission:
to the opposite side through the middle, the same timing, so that they would meet there. The
companions deconflict (companion.deconfliction): the demo prints the minimum separation planned
(the committed trajectories, sampled) and flown (telemetry) for each pair, the deconfliction
replans and start delays with their latency, and writes a top view to out/.

A client of the companions, over Zenoh only, like the single-vehicle demo.
"""

from __future__ import annotations

import contextlib
import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import numpy as np
import zenoh

from companion.geodesy import Placement, ned_to_lla
from companion.traffic import Claim, read_claim

REPO = Path(__file__).resolve().parent.parent
ORIGIN = (47.397742, 8.545594, 488.0)
R = 10.0
SEPARATION = 3.0
POPUP_AFTER = 3.0  # s after the missions: a pop-up obstacle on drone1's last leg


def _port(kind: int = socket.SOCK_STREAM) -> int:
    with socket.socket(socket.AF_INET, kind) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class FleetRig:
    def __init__(self, n: int, out: Path) -> None:
        self.n, self.out = n, out
        self.names = [f"drone{i + 1}" for i in range(n)]
        self.unit = {v: np.array([np.cos(a), np.sin(a), 0.0]) for v, a in
                     zip(self.names, np.deg2rad(90.0 + 360.0 * np.arange(n) / n), strict=True)}
        self.procs: list[subprocess.Popen[bytes]] = []
        self.lock = threading.Lock()
        self.statuses: dict[str, dict[str, Any]] = {}
        self.events: list[dict[str, Any]] = []
        self.committed: dict[tuple[str, int], tuple[float, Claim]] = {}
        self.positions: dict[str, list[tuple[float, np.ndarray]]] = {v: [] for v in self.names}
        self.session: Any = None

    def start(self) -> None:
        self.out.mkdir(parents=True, exist_ok=True)
        router = _port()
        env = {**os.environ, "PYTHONUNBUFFERED": "1", "PYTHONPATH": str(REPO)}

        def spawn(name: str, *cmd: str) -> None:
            self.procs.append(subprocess.Popen([sys.executable, *cmd], cwd=REPO, env=env, stdout=subprocess.DEVNULL,
                                               stderr=open(self.out / f"{name}.log", "wb")))  # noqa: SIM115

        spawn("router", "-m", "companion", "router", "--listen", f"tcp/127.0.0.1:{router}")
        for v in self.names:
            mav = _port(socket.SOCK_DGRAM)
            home = ned_to_lla(R * self.unit[v], ORIGIN)
            spawn(f"{v}-mock", "-m", "sitl_mock", "--endpoint", f"udpin:127.0.0.1:{mav}", "--px4-ready-after", "0",
                  "--response", "ideal", "--home", ",".join(f"{x:.9f}" for x in home))
            cfg = self.out / f"{v}.toml"
            cfg.write_text(f"""[vehicle]
id = "{v}"
[zenoh]
mode = "client"
connect = ["tcp/127.0.0.1:{router}"]
multicast_scouting = false
[mavlink]
url = "udpout:127.0.0.1:{mav}"
[planner]
executor = "thread"
[safety]
hold_confirm = 0.5
exit_timeout = 4.0
[fleet]
origin = [{ORIGIN[0]}, {ORIGIN[1]}, {ORIGIN[2]}]
clock_tolerance = 0.05
separation = {SEPARATION}
max_delay = 0.1
""")
            spawn(v, "-m", "companion", "run", "--config", str(cfg))
        zc = zenoh.Config()
        zc.insert_json5("mode", '"client"')
        zc.insert_json5("connect/endpoints", json.dumps([f"tcp/127.0.0.1:{router}"]))
        zc.insert_json5("scouting/multicast/enabled", "false")
        deadline = time.monotonic() + 20
        while self.session is None:
            try:
                self.session = zenoh.open(zc)
            except zenoh.ZError:
                if time.monotonic() > deadline:
                    raise
                time.sleep(0.2)
        self.session.declare_subscriber("bezier/*/status", self._status)
        self.session.declare_subscriber("bezier/*/events", self._event)
        self.session.declare_subscriber("bezier/*/trajectory", self._trajectory)
        self.session.declare_subscriber("bezier/*/telemetry", self._telemetry)

    def _status(self, sample: Any) -> None:
        with contextlib.suppress(ValueError), self.lock:
            self.statuses[str(sample.key_expr).split("/")[1]] = json.loads(sample.payload.to_bytes())

    def _event(self, sample: Any) -> None:
        with contextlib.suppress(ValueError), self.lock:
            self.events.append({"vehicle": str(sample.key_expr).split("/")[1], **json.loads(sample.payload.to_bytes())})

    def _trajectory(self, sample: Any) -> None:
        v = str(sample.key_expr).split("/")[1]
        with contextlib.suppress(ValueError):
            claim = read_claim(json.loads(sample.payload.to_bytes()), v)
            if claim is not None and claim.committed:
                with self.lock:
                    self.committed.setdefault((v, claim.seq), (time.time(), claim))

    def _telemetry(self, sample: Any) -> None:
        v = str(sample.key_expr).split("/")[1]
        with contextlib.suppress(ValueError):
            body = json.loads(sample.payload.to_bytes())
            fl = (self.statuses.get(v) or {}).get("fleet") or {}
            if body.get("position") is not None and fl.get("placed"):
                pl = Placement(np.asarray(fl["offset_ned"]), np.asarray(fl["rotation"]))
                with self.lock:
                    self.positions[v].append((float(body["time"]), pl.to_fleet(body["position"])))

    def wait(self, pred: Any, timeout: float, what: str) -> None:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            with self.lock:
                if all(pred(self.statuses.get(v) or {}) for v in self.names):
                    return
            time.sleep(0.1)
        raise RuntimeError(f"{what}: not within {timeout:g} s (logs in {self.out})")

    def put(self, v: str, kind: str, body: dict[str, Any]) -> None:
        self.session.put(f"bezier/{v}/{kind}", json.dumps(body).encode())

    def stop(self) -> None:
        if self.session is not None:
            with contextlib.suppress(Exception):
                self.session.close()
        for p in reversed(self.procs):
            p.terminate()
        for p in self.procs:
            try:
                p.wait(10)
            except subprocess.TimeoutExpired:
                p.kill()


def _min_planned(a: Claim, b: Claim, t0: float) -> float:
    t1 = max(a.trajectory.times[-1], b.trajectory.times[-1])
    ts = np.linspace(t0, t1, 800)

    def at(c: Claim, t: float) -> np.ndarray:
        tr = c.trajectory
        return np.asarray(tr.evaluate(float(np.clip(t, tr.times[0], tr.times[-1]))))

    return float(min(np.linalg.norm(at(a, t) - at(b, t)) for t in ts))


def run(n: int, out: Path, plots: bool = True) -> int:
    print(f"bezier-companion fleet demo: one Zenoh router, {n} mock autopilots, {n} companions; logs in {out}/")
    rig = FleetRig(n, out)
    popup_centre: np.ndarray | None = None
    popup_since = 0
    try:
        rig.start()
        rig.wait(lambda s: s.get("link") and (s.get("fleet") or {}).get("placed"), 60, "companions linked and placed")
        for v in rig.names:
            rig.put(v, "command", {"command": "arm"})
        rig.wait(lambda s: s.get("armed"), 30, "armed")
        for v in rig.names:
            rig.put(v, "command", {"command": "takeoff", "altitude": 3.0})
        rig.wait(lambda s: s.get("state") == "READY" and s.get("airborne"), 30, "airborne")
        time.sleep(0.5)
        with rig.lock:
            z = float(np.mean([p[-1][1][2] for p in rig.positions.values() if p]))
        t0 = time.time()
        since = len(rig.events)
        print(f"- crossing missions sent to {', '.join(rig.names)} at once (to the opposite side, timed to meet "
              "in the middle)")
        for v in rig.names:
            u = rig.unit[v]
            rig.put(v, "mission", {"id": f"cross-{v}", "origin": "fleet", "durations": [5.0, 3.0],
                                   "waypoints": [(k * R * u + [0, 0, z]).round(3).tolist() for k in (0.5, -0.5, -1.0)]})
        # a pop-up obstacle on drone1's last leg, once the crossing is under way: a local replan
        # against the obstacle and the other vehicles' committed trajectories at once
        time.sleep(POPUP_AFTER)
        u = rig.unit[rig.names[0]]
        centre = popup_centre = -0.75 * R * u + [0, 0, z]
        corners = [np.add(centre, [dn, de, dd]).round(3).tolist() for dn in (-0.5, 0.5) for de in (-0.5, 0.5)
                   for dd in (-2.0, 2.0)]
        popup_since = len(rig.events)
        rig.put(rig.names[0], "obstacles", {"origin": "fleet", "add": [{"id": "popup", "vertices": corners}]})
        # until no vehicle flies a plan any more (each completed, stopped or refused), 90 s at most:
        # the table below says how each ended
        time.sleep(1.0)
        with contextlib.suppress(RuntimeError):
            rig.wait(lambda s: s.get("state") not in ("STREAMING", "BRAKING"), 90, "crossings over")
        time.sleep(0.5)
        with rig.lock:
            events = rig.events[since:]
            committed = sorted(rig.committed.values(), key=lambda x: x[0])
            tracks = {v: [(t, p) for t, p in ps if t >= t0] for v, ps in rig.positions.items()}
            statuses = dict(rig.statuses)
    finally:
        rig.stop()
    accepted = {e["vehicle"]: e for e in events if e.get("type") == "accepted" and e.get("key") == "mission"}
    complete = {e["vehicle"] for e in events if e.get("type") == "mission_complete"}
    why_not = {e["vehicle"]: f"{e.get('type')}: {e.get('message', '')[:140]}" for e in events
               if e.get("type") in ("rejected", "braking", "stalled") and e["vehicle"] not in complete}
    lost = [e for e in events if e.get("type") == "fleet" and "deconfliction" in e.get("message", "")]
    with rig.lock:
        popup = [e for e in rig.events[popup_since:] if e["vehicle"] == rig.names[0]
                 and e.get("type") in ("replanned", "braking", "obstacles_clear")]
    print("\nvehicle  mission  plan_ms  committed_after_ms  start_delay_s  deconfliction_replans")
    committed_after: dict[str, float | None] = {}
    for v in rig.names:
        a = accepted.get(v, {})
        dec = ((statuses.get(v) or {}).get("fleet") or {}).get("deconfliction") or {}
        # from the mission's put to the accepted event (planning, the proposals, the waits, the replans)
        committed_after[v] = round((float(a["time"]) - t0) * 1000, 1) if "time" in a else None
        print(f"{v:8} {'done' if v in complete else 'FAILED':8} {a.get('plan_ms', '-')!s:8} "
              f"{committed_after[v]!s:19} {a.get('fleet_delay', 0)!s:14} {dec.get('replans', '-')}")
    latest: dict[str, Claim] = {}
    for _t, c in committed:
        latest[c.vehicle] = c
    allowance = (statuses.get(rig.names[0]) or {}).get("tracking_allowance", 0.0)
    print(f"\npair             planned_min_m  flown_min_m  (separation {SEPARATION:g} m, tracking allowance "
          f"{allowance} m)")
    worst_flown = np.inf
    pairs = []
    for i, va in enumerate(rig.names):
        for vb in rig.names[i + 1:]:
            planned = _min_planned(latest[va], latest[vb], t0) if va in latest and vb in latest else float("nan")
            tb = np.array([t for t, _ in tracks[vb]])
            pb = np.array([p for _, p in tracks[vb]])
            flown = np.inf
            for t, p in tracks[va]:
                k = int(np.argmin(np.abs(tb - t))) if len(tb) else -1
                if k >= 0 and abs(tb[k] - t) <= 0.05:
                    flown = min(flown, float(np.linalg.norm(p - pb[k])))
            worst_flown = min(worst_flown, flown)
            pairs.append((va, vb, planned, flown))
            print(f"{va + '-' + vb:16} {planned:13.2f}  {flown:11.2f}")
    for e in popup[:2]:
        print(f"\npop-up obstacle on {rig.names[0]}'s path: {e['type']}: {e['message'][:200]}")
    if not popup:
        print(f"\npop-up obstacle on {rig.names[0]}'s path: no replan seen")
    for v, why in sorted(why_not.items()):
        print(f"\n{v} did not complete its crossing: {why}")
    print(f"\ndeconfliction events: {len(lost)}")
    for e in lost:
        print(f"  {e['vehicle']}: {e['message'][:160]}")
    if plots:
        png = _plot(rig, tracks, latest, t0, out / "fleet_top.png", popup_centre)
        print(f"\nfigure: {png}")
    ok = complete == set(rig.names) and worst_flown >= SEPARATION - allowance
    (out / "fleet_summary.json").write_text(json.dumps({
        "ok": ok, "pairs": [{"a": a, "b": b, "planned_min_m": p, "flown_min_m": f} for a, b, p, f in pairs],
        "start_delays": {v: accepted.get(v, {}).get("fleet_delay", 0) for v in rig.names},
        "plan_ms": {v: accepted.get(v, {}).get("plan_ms") for v in rig.names},
        "committed_after_ms": committed_after}, indent=2))
    print("\nfleet demo " + ("OK: every pair kept its separation" if ok else "FAILED"))
    return 0 if ok else 1


def _plot(rig: FleetRig, tracks: dict[str, list[tuple[float, np.ndarray]]], latest: dict[str, Claim], t0: float,
          path: Path, popup: np.ndarray | None = None) -> Path:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.patches import Rectangle

    fig, ax = plt.subplots(figsize=(6, 6))
    for v in rig.names:
        pts = np.array([p for _, p in tracks[v]]) if tracks[v] else np.zeros((0, 3))
        line = ax.plot(pts[:, 1], pts[:, 0], label=f"{v} flown", lw=2)[0] if len(pts) else None
        if v in latest:
            tr = latest[v].trajectory
            ts = np.linspace(max(tr.times[0], t0), tr.times[-1], 300)
            pl = np.array([tr.evaluate(float(t)) for t in ts])
            ax.plot(pl[:, 1], pl[:, 0], "--", color=None if line is None else line.get_color(), lw=1,
                    label=f"{v} committed")
        home = R * rig.unit[v]
        ax.plot(home[1], home[0], "o", color="k", ms=4)
    if popup is not None:  # the pop-up obstacle, 1 m square
        ax.add_patch(Rectangle((popup[1] - 0.5, popup[0] - 0.5), 1.0, 1.0, color="0.3", alpha=0.6,
                                   label="pop-up obstacle"))
    ax.set_xlabel("east (m, fleet frame)")
    ax.set_ylabel("north (m, fleet frame)")
    ax.set_aspect("equal")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    ax.set_title(f"{len(rig.names)} crossing vehicles, separation {SEPARATION:g} m")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return path
