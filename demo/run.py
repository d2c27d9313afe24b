"""`python -m demo` (or `python -m companion demo`): the whole chain on this machine, no hardware.

Starts the mock autopilot (sitl_mock) and the companion service as subprocesses on free loopback
ports, joins their Zenoh network as a peer, and flies the paper's two scenarios in real time:
scenario 1, then scenario 2 with a pop-up obstacle published mid-flight and a waypoint moved out
of its way. It prints live progress and a summary table, writes figures to out/demo/, and exits
non-zero if a mission was not flown as planned.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import json
import math
import queue
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from companion.wire.frames import swap_points
from demo import report as rep
from demo.rig import (
    ROOT,
    TAKEOFF_ALTITUDE,
    Peer,
    Rig,
    Sample,
    rig,
)
from planner_core import Trajectory

EXAMPLES = ROOT / "examples"
UP = np.array([0.0, 0.0, 1.0])  # ENU
# m: the paper's scenarios touch z = 0; fly them this much higher (ENU, up), which is also where
# the companion's takeoff leaves the vehicle
LIFT = TAKEOFF_ALTITUDE
MAX_TRACKING_ERROR = 1.0  # m: beyond this the flight is not "as planned"


# --- scenarios -------------------------------------------------------------------------------


def load_example(name: str) -> dict[str, Any]:
    obj: dict[str, Any] = json.loads((EXAMPLES / name).read_text())
    obj.pop("description", None)
    return obj


def lift_region(region: dict[str, Any], dz: float) -> dict[str, Any]:
    """An obstacle/corridor translated up by dz (ENU): A(x - d) <= b  ->  b' = b + A d."""
    out = dict(region)
    if "vertices" in region:
        out["vertices"] = (np.asarray(region["vertices"], dtype=float) + dz * UP).tolist()
    if "A" in region:
        A = np.asarray(region["A"], dtype=float)
        out["b"] = (np.asarray(region["b"], dtype=float) + A @ (dz * UP)).tolist()
    return out


def lifted_mission(scenario: dict[str, Any], mission_id: str, dz: float = LIFT) -> dict[str, Any]:
    if scenario.get("frame", "enu") != "enu":
        raise ValueError("demo scenarios are written in ENU (z up)")
    m = {k: v for k, v in scenario.items() if k not in ("corridors",)}
    m["id"] = mission_id
    m["frame"] = "enu"
    m["waypoints"] = (np.asarray(scenario["waypoints"], dtype=float) + dz * UP).tolist()
    m["obstacles"] = [lift_region(o, dz) for o in scenario.get("obstacles", [])]
    if "map" in scenario:
        lo = np.asarray(scenario["map"]["min"], dtype=float) + dz * UP
        hi = np.asarray(scenario["map"]["max"], dtype=float) + dz * UP
        m["map"] = {"min": lo.tolist(), "max": hi.tolist()}
    # The demo flies the vehicle onto waypoint 0 first (see transit), so the scenario starts there.
    m["start"] = "first_waypoint"
    m["origin"] = "home"  # z above the ground the vehicle took off from, whatever the local origin
    return m


def transit(mission: dict[str, Any], here: np.ndarray | None, altitude: float = 6.0) -> list[dict[str, Any]]:
    """Missions that climb to `altitude` (above every obstacle), cross, and descend onto the
    mission's waypoint 0, each from rest where the previous one stopped. The crossing has
    collinear waypoints every few metres, so the planner carries speed along it without the
    sideways swing a minimum-snap curve takes through a corner."""
    goal = np.asarray(mission["waypoints"][0], dtype=float)
    start = np.array([0.0, 0.0, LIFT]) if here is None else np.asarray(here, dtype=float)
    top_a = np.array([start[0], start[1], altitude])
    top_b = np.array([goal[0], goal[1], altitude])
    n = max(1, int(np.ceil(np.linalg.norm(top_b - top_a) / 4.0)))
    legs = [[start, top_a], [top_a + (top_b - top_a) * k / n for k in range(n + 1)], [top_b, goal]]
    out: list[dict[str, Any]] = []
    for i, pts in enumerate(legs):
        first = here is None and not out  # on the ground: the companion takes off first
        out.append({"id": f"transit-{mission['id']}-{i}", "frame": "enu", "origin": "home",
                    "start": "current" if first else "first_waypoint",
                    "waypoints": [[round(float(v), 4) for v in p] for p in (pts[1:] if first else pts)],
                    "bounds": {"velocity": 5.0, "acceleration": 4.0, "jerk": 10.0, "snap": 40.0}})
    return out


def clear_of_route(popup: dict[str, Any], mission: dict[str, Any], allowance: float = 0.0,
                   margin: float = 0.2) -> dict[str, Any]:
    """The pop-up obstacle moved east until the leg from waypoint 1 (x = const) clears it.

    examples/scenario2_popup.json centres the box on x = 15, the line both waypoint 1 and the
    moved waypoint 2 lie on: inflated by the vehicle radius it contains the original waypoint 2
    and cuts the leg to the moved one, so no convex corridor exists and the companion (rightly)
    brakes. The paper's intent is an obstacle that invalidates the flown curve, which bulges east
    of that line, so the demo keeps the box's size and moves it east just enough. The companion
    inflates obstacles by the radius plus its tracking allowance (`allowance`, [planner]
    tracking_allowance): moved by the radius alone, the inflated box still cut the leg and every
    run braked ("no safe plan": seen on real ArduCopter and on the mock).
    """
    radius = float(mission.get("vehicle_radius", 0.3)) + allowance
    x_line = float(mission["waypoints"][1][0])
    out: dict[str, Any] = json.loads(json.dumps(popup))
    for ob in out["obstacles"]:
        A = np.asarray(ob["A"], dtype=float)
        b = np.asarray(ob["b"], dtype=float)
        west = int(np.argmin(A[:, 0]))  # the -x face: -x <= b_west, i.e. x >= -b_west
        x_min = -b[west] / -A[west, 0]
        # the corridor builder wants a vehicle's width (2 radii) between a leg and an obstacle
        shift = max(0.0, x_line + 2 * radius + margin - x_min)
        ob["b"] = (b + A @ np.array([shift, 0.0, 0.0])).tolist()
    return out


def lifted_obstacles(popup: dict[str, Any], dz: float = LIFT) -> dict[str, Any]:
    return {
        "frame": "enu",
        "origin": "home",
        "add": [{"id": f"popup-{i}", **lift_region(o, dz)} for i, o in enumerate(popup["obstacles"])],
    }


def lifted_change(change: dict[str, Any], dz: float = LIFT) -> dict[str, Any]:
    out = {k: v for k, v in change.items() if k != "description"}
    out["frame"] = "enu"
    out["origin"] = "home"
    for key in ("move_waypoint", "insert_waypoint"):
        if key in out:
            out[key] = {**out[key], "position": (np.asarray(out[key]["position"]) + dz * UP).tolist()}
    return out


# --- flying ----------------------------------------------------------------------------------


Trigger = Callable[[float, np.ndarray | None], bool]


@dataclass
class Action:
    """Something to publish mid-flight, once `when(seconds streaming, position ENU)` holds."""

    when: Trigger
    topic: str
    payload: dict[str, Any]
    label: str
    sent: float | None = None


def after(seconds: float) -> Trigger:
    return lambda t, pos: t >= seconds


@dataclass
class FlightOutcome:
    ok: bool
    reason: str
    t_put: float
    trajectories: list[Sample]  # every trajectory published after the mission was put
    t_stream: float | None
    t_done: float | None
    actions: list[Action]
    events: list[Sample]
    # (monotonic time, lead s) from the companion's status: what the setpoints were sampled ahead by
    leads: list[tuple[float, float]] = dataclasses.field(default_factory=list)


class Progress:
    def __init__(self) -> None:
        self.tty = sys.stdout.isatty()
        self._last = 0.0

    def show(self, text: str, force: bool = False) -> None:
        now = time.monotonic()
        if self.tty:
            sys.stdout.write("\r\033[K" + text)
            sys.stdout.flush()
        elif force or now - self._last >= 2.0:
            print("  " + text, flush=True)
            self._last = now

    def done(self) -> None:
        if self.tty:
            sys.stdout.write("\n")
            sys.stdout.flush()


def _status_line(name: str, status: Any, pos: np.ndarray | None, elapsed: float) -> str:
    st = status if isinstance(status, dict) else {}
    where = "" if pos is None else f"  ENU from home [{pos[0]:6.2f} {pos[1]:6.2f} {pos[2]:5.2f}] m"
    progress = st.get("progress")
    prog = f" {100 * progress:3.0f}%" if isinstance(progress, int | float) else ""
    err = st.get("tracking_error")
    track = f"  err {err:.2f} m" if isinstance(err, int | float) else ""
    return f"[{name}] t={elapsed:5.1f}s {st.get('state', '?'):<9}{prog}{where}{track}"


FAIL_EVENTS = {"rejected", "refused", "braking", "aborted"}
AIRBORNE = {"READY", "HOLDING", "STREAMING", "BRAKING"}


def fly(r: Rig, mission: dict[str, Any], actions: list[Action], timeout: float, progress: Progress) -> FlightOutcome:
    """Publish a mission (and `start` when on the ground), run the actions, wait for completion."""
    _drain(r.peer)
    status = r.peer.query("status") or {}
    t_put = r.peer.put("mission", mission)
    need_start = status.get("state") not in AIRBORNE
    trajectories: list[Sample] = []
    events: list[Sample] = []
    leads: list[tuple[float, float]] = []
    t_stream: float | None = None
    t_done: float | None = None
    reason = ""
    deadline = t_put + timeout
    name = mission["id"]
    while time.monotonic() < deadline and not reason and t_done is None:
        dead = r.check_alive()
        if dead:
            reason = dead
            break
        try:
            s: Sample | None = r.peer.samples.get(timeout=0.05)
        except queue.Empty:
            s = None
        if s is not None and s.topic == "trajectory":
            trajectories.append(s)
        elif s is not None and s.topic == "events":
            events.append(s)
            ev = s.data if isinstance(s.data, dict) else {}
            kind = str(ev.get("type", ""))
            if kind == "accepted" and ev.get("key") == "mission" and need_start:
                need_start = False
                r.peer.put("command", {"command": "start"})
                progress.show(f"[{name}] mission loaded; sent 'start' (arm, take off, fly)", force=True)
                progress.done()
            elif t_stream is None and (
                (kind == "state" and ev.get("to") == "STREAMING")
                # already streaming the previous mission: no state change, but this event
                or (kind == "accepted" and ev.get("mission") == name and "plan_ms" in ev)
            ):
                t_stream = s.mono
            elif kind == "mission_complete" and ev.get("mission") in (name, None):
                t_done = s.mono
            elif kind in FAIL_EVENTS or (kind == "state" and ev.get("to") in ("FAILSAFE", "PILOT", "IDLE")):
                reason = f"{kind}: {ev.get('message', '')}"
        now = time.monotonic()
        tel = r.peer.latest.get("telemetry")
        pos = _enu_position(tel.data if tel else None, r.home)
        if t_stream is not None:
            for a in actions:
                if a.sent is None and a.when(now - t_stream, pos):
                    a.sent = r.peer.put(a.topic, a.payload)
                    progress.show(f"[{name}] published {a.label}", force=True)
                    progress.done()
        st = r.peer.latest.get("status")
        if st is not None and isinstance(st.data, dict) and isinstance(st.data.get("lead_ms"), int | float) and (
                not leads or leads[-1][0] != st.mono):
            leads.append((st.mono, float(st.data["lead_ms"]) / 1000.0))
        progress.show(_status_line(name, st.data if st else None, pos, now - t_put))
    progress.done()
    if not reason and t_done is None:
        reason = f"timeout after {timeout:.0f} s"
    return FlightOutcome(not reason, reason, t_put, trajectories, t_stream, t_done, actions, events, leads)


def _enu_position(telemetry: Any, home: np.ndarray) -> np.ndarray | None:
    """Telemetry's local NED position as the demo's missions give positions: ENU from home."""
    if isinstance(telemetry, dict) and isinstance(telemetry.get("position"), list):
        with contextlib.suppress(ValueError, TypeError):
            return swap_points(np.asarray(telemetry["position"], dtype=float) - home)
    return None


def _drain(peer: Peer) -> None:
    with contextlib.suppress(queue.Empty):
        while True:
            peer.samples.get_nowait()


# --- analysis --------------------------------------------------------------------------------


def read_flown(log: Path) -> tuple[rep.Flown, np.ndarray, np.ndarray]:
    """States (t, pos, vel) and applied setpoints (t, pos) from the mock's flight log (NED)."""
    flown, sp_t, sp_p, _ = read_flown_sent(log)
    return flown, sp_t, sp_p


def read_flown_sent(log: Path) -> tuple[rep.Flown, np.ndarray, np.ndarray, np.ndarray]:
    """read_flown, and each applied setpoint's send time in the companion's clock (its
    time_boot_ms, s; NaN where the mock did not log it)."""
    st_t, st_p, st_v, sp_t, sp_p, sp_c = [], [], [], [], [], []
    with open(log, encoding="utf-8") as fh:
        for line in fh:
            if not line.strip():
                continue
            rec = json.loads(line)
            if rec.get("type") == "state":
                st_t.append(rec["t"])
                st_p.append(rec["pos"])
                st_v.append(rec["vel"])
            elif rec.get("type") == "setpoint" and rec.get("applied") and _full(rec.get("pos")):
                sp_t.append(rec["t"])
                sp_p.append(rec["pos"])
                ms = rec.get("time_boot_ms")
                sp_c.append(float(ms) / 1000.0 if isinstance(ms, int | float) else math.nan)
    flown = rep.Flown(np.asarray(st_t, float), np.asarray(st_p, float).reshape(-1, 3),
                      np.asarray(st_v, float).reshape(-1, 3))
    return flown, np.asarray(sp_t, float), np.asarray(sp_p, float).reshape(-1, 3), np.asarray(sp_c, float)


def setpoint_leads(sp_t: np.ndarray, tau_sp: np.ndarray, sent: np.ndarray, leads: list[tuple[float, float]],
                   mono_to_sim: Callable[[float], float], fallback: float,
                   moving: np.ndarray | None = None) -> np.ndarray:
    """How far ahead of its own time each setpoint was sampled (s), whatever the lead did
    (fixed, or "auto" changing in flight). Setpoint i was the plan at tau_i = c_i - c0 +
    lead_i, with c_i its send time in the companion's clock (time_boot_ms) and c0 the
    companion's time base in that clock: so tau_i - c_i = lead_i - c0 follows the lead
    setpoint by setpoint, and the status samples of the lead fix the constant c0 (a median
    over all of them). tau_i is known where the plan moves (`moving`: at rest a setpoint
    matches any time of the hover); elsewhere the lead is interpolated. Without those:
    `fallback` for every setpoint."""
    u = tau_sp - sent
    ok = np.isfinite(u) if moving is None else np.isfinite(u) & moving
    if not leads or ok.sum() < 10:
        return np.full(len(sp_t), fallback)
    s = np.array([mono_to_sim(m) for m, _ in leads])
    lv = np.array([v for _, v in leads])
    inside = (s >= sp_t[ok][0]) & (s <= sp_t[ok][-1])
    if not inside.any():
        return np.full(len(sp_t), fallback)
    c0 = float(np.median(lv[inside] - np.interp(s[inside], sp_t[ok], u[ok])))
    out: np.ndarray = np.where(ok, u + c0, np.interp(sp_t, sp_t[ok], u[ok] + c0))
    return out


def _full(vec: Any) -> bool:
    return isinstance(vec, list) and len(vec) == 3 and all(v is not None for v in vec)


def trajectory_of(sample: Sample) -> Trajectory:
    from planner_core import trajectory_from_dict

    data = sample.data
    body = data.get("trajectory", data) if isinstance(data, dict) else data
    keep = {k: body[k] for k in ("format", "frame", "degree", "segments", "stats") if k in body}
    return trajectory_from_dict(keep)


def _event_values(events: list[Sample], kind: str, key: str) -> list[tuple[Sample, float]]:
    out = []
    for e in events:
        if isinstance(e.data, dict) and e.data.get("type") == kind and isinstance(e.data.get(key), int | float):
            out.append((e, float(e.data[key])))
    return out


def analyse(name: str, mission: dict[str, Any], outcome: FlightOutcome, r: Rig,
            mono_to_sim: Callable[[float], float], lead: float = 0.0) -> rep.MissionResult:
    result = rep.MissionResult(name=name, ok=outcome.ok, reason=outcome.reason)
    result.bounds = rep.bounds_matrix(mission.get("bounds"), "enu")
    planned = [v for e, v in _event_values(outcome.events, "accepted", "plan_ms") if e.data.get("mission") == name]
    result.plan_ms = planned[-1] if planned else None
    if outcome.t_stream is not None:
        result.plan_latency = outcome.t_stream - outcome.t_put
    result.replan_ms = [v for _, v in _event_values(outcome.events, "replanned", "replan_ms")]
    # the companion times each in-flight message to the first setpoint of the plan it caused
    result.message_to_setpoint_ms = [v for e, v in _event_values(outcome.events, "latency", "latency_ms")
                                     if not str(e.data.get("what", "")).startswith("mission")]
    samples = mission_trajectories(outcome.trajectories, mission, r.home)
    if samples:
        (r.out / f"{name}_trajectories.json").write_text(json.dumps([s.data for s in samples]))
        result.trajectories = [trajectory_of(s) for s in samples]
        result.stats = dict(result.trajectories[0].stats)
    for a in outcome.actions:
        if a.sent is None:
            if result.ok:
                result.ok, result.reason = False, f"the {a.label} was never published"
            continue
        later = [s for s in samples if s.mono > a.sent]
        if later:
            result.replan_latencies[a.label] = later[0].mono - a.sent
        elif result.ok:
            result.ok, result.reason = False, f"no new trajectory after the {a.label}"
    if outcome.t_stream is not None and outcome.t_done is not None:
        result.flight_time = outcome.t_done - outcome.t_stream
    if not result.trajectories:
        if result.ok:
            result.ok, result.reason = False, "no trajectory received"
        return result
    first, final = result.trajectories[0], result.trajectories[-1]
    result.peaks_planned = np.max([rep.planned_peaks(t) for t in result.trajectories], axis=0)
    time.sleep(0.7)  # the mock flushes its log every 0.5 s
    flown, sp_t, sp_p, sp_c = read_flown_sent(r.flight_log)
    if len(sp_t) < 10 or len(flown.t) < 10:
        result.ok, result.reason = False, "the mock logged no applied setpoints"
        return result
    s_stream = mono_to_sim(outcome.t_stream if outcome.t_stream is not None else outcome.t_put)
    s_first_change = mono_to_sim(samples[1].mono) if len(samples) > 1 else (
        mono_to_sim(outcome.t_done) if outcome.t_done is not None else s_stream + first.t_end - first.t0)
    window = (sp_t >= s_stream) & (sp_t <= s_first_change)
    if window.sum() < 10:
        window = sp_t >= s_stream
    offset = rep.align_offset(first, sp_t[window], sp_p[window], s_stream - first.t_end, s_stream - first.t0)
    starts = replan_starts(samples, outcome.events, mono_to_sim, offset)
    tau_end = (mono_to_sim(outcome.t_done) - offset) if outcome.t_done is not None else final.t_end
    flying = (sp_t >= s_stream) & (sp_t <= offset + tau_end)
    if flying.sum() < 10:
        result.ok, result.reason = False, "no setpoints of this mission in the mock's log"
        return result
    sp_t, sp_p, sp_c = sp_t[flying], sp_p[flying], sp_c[flying]
    # (an auto lead moves the setpoints up to [setpoints] lead_max along the plan in flight)
    sp_raw, sp_off = rep.local_offsets(result.trajectories, starts, sp_t, sp_p, offset, search=0.6)
    # A setpoint sampled `lead` ahead matches the plan `lead` later than its own time: the
    # flown position is compared with the plan at its own time, not with the setpoint, with
    # each setpoint's own lead (the auto lead changes in flight).
    tau_sp = sp_t - sp_raw
    moving = np.linalg.norm(rep.stitched(result.trajectories, starts, tau_sp, 1), axis=1) >= 0.3
    result.leads = setpoint_leads(sp_t, tau_sp, sp_c, outcome.leads, mono_to_sim, lead, moving)
    sp_off = sp_off + rep.running_median(result.leads)
    result.starts = starts
    result.tau_stream = s_stream - offset
    result.tracking = rep.tracking_error(result.trajectories, starts, flown, sp_t, sp_off,
                                         result.tau_stream, tau_end)
    # every setpoint the mock received must be a point of the planned trajectory (float32 on
    # the wire): checks frames, splicing and sampling end to end
    dev = np.linalg.norm(sp_p - rep.stitched(result.trajectories, starts, sp_t - sp_raw), axis=1)
    result.setpoint_deviation = float(dev.max())
    offset = result.tracking.offset
    result.peaks_flown = rep.flown_peaks(flown, s_stream, offset + tau_end)
    if result.ok and not all(t.stats.get("verified", True) for t in result.trajectories):
        result.ok, result.reason = False, "a trajectory was not verified"
    if result.ok and not (result.tracking.max <= MAX_TRACKING_ERROR):
        result.ok, result.reason = False, f"tracking error {result.tracking.max:.2f} m > {MAX_TRACKING_ERROR} m"
    return result


def local_ned(points: Any, mission: dict[str, Any], home: np.ndarray) -> np.ndarray:
    """A message's positions in the autopilot's local NED frame (what the plans and the mock's
    log are in): ENU swapped, home-relative ones shifted by home (NED)."""
    pts = np.asarray(points, dtype=float)
    if mission.get("frame", "ned") == "enu":
        pts = swap_points(pts)
    return pts + home if mission.get("origin", "local") == "home" else pts


def local_enu(points: Any, mission: dict[str, Any], home: np.ndarray) -> np.ndarray:
    """A message's ENU positions in the local frame, as ENU (for the figures)."""
    return swap_points(local_ned(points, mission, home))


def mission_trajectories(samples: list[Sample], mission: dict[str, Any], home: np.ndarray) -> list[Sample]:
    """The mission's trajectory and its replans: those ending at the mission's last waypoint.

    (Zenoh does not order messages across keys, so "the trajectory published just before the
    STREAMING event" is not a reliable way to find it.)
    """
    end = local_ned(mission["waypoints"][-1], mission, home)
    out = []
    for s in samples:
        with contextlib.suppress(KeyError, IndexError, TypeError, ValueError):
            last = np.asarray(s.data["segments"][-1]["control_points"][-1], dtype=float)
            if float(np.linalg.norm(last - end)) < 1e-3:
                out.append(s)
    return out


def replan_starts(samples: list[Sample], events: list[Sample], mono_to_sim: Callable[[float], float],
                  offset: float) -> list[float]:
    """Trajectory time from which each replan is the active trajectory: its split time, as the
    companion reports it (it equals its predecessor before that); else its arrival time."""
    splits = [float(e.data["split_time"]) for e in events
              if isinstance(e.data, dict) and e.data.get("type") == "replanned"
              and isinstance(e.data.get("split_time"), int | float) and e.mono >= samples[0].mono]
    if len(splits) == len(samples) - 1:
        return [-np.inf, *splits]
    return [-np.inf] + [mono_to_sim(s.mono) - offset for s in samples[1:]]


def sim_clock(r: Rig) -> Callable[[float], float]:
    """Map this process's monotonic clock to the mock's simulated clock (speed 1)."""
    from sitl_mock.control import ControlClient

    best: tuple[float, float] | None = None
    with contextlib.closing(ControlClient("127.0.0.1", r.control_port)) as client:
        for _ in range(5):
            a = time.monotonic()
            state = client.state()
            b = time.monotonic()
            if best is None or b - a < best[0]:
                best = (b - a, float(state["t"]) - (a + b) / 2)
    assert best is not None
    offset = best[1]
    return lambda mono: mono + offset


def figures(name: str, title: str, mission: dict[str, Any], result: rep.MissionResult, r: Rig,
            popup: dict[str, Any] | None = None, change: dict[str, Any] | None = None) -> list[Path]:
    if not result.trajectories:
        return []
    # the scene in the local frame (ENU), where the plans and the flown path are
    scene = rep.Scene(waypoints=local_enu(mission["waypoints"], mission, r.home))
    scene.obstacles = [local_enu(rep.region_vertices_enu(o, "enu"), mission, r.home)
                       for o in mission.get("obstacles", [])]
    if popup is not None:
        scene.popups = [local_enu(rep.region_vertices_enu(o, "enu"), popup, r.home) for o in popup["add"]]
    final = result.trajectories[-1]
    if final.corridors is not None:
        verts = [rep.polytope_vertices(c.A, c.b) for c in final.corridors if c is not None]
        scene.corridors = [swap_points(v) for v in verts if len(v)]
    if change is not None and "move_waypoint" in change:
        mv = change["move_waypoint"]
        scene.moved = [(scene.waypoints[mv["index"]], local_enu(mv["position"], change, r.home))]
    planned = [("planned", final)]
    if len(result.trajectories) > 1:
        planned = [("first plan", result.trajectories[0]), ("after replans", final)]
    flown_enu = flown_tau = None
    flown: rep.Flown | None = None
    if result.tracking is not None:
        flown, _, _ = read_flown(r.flight_log)
        off = result.tracking.offset
        mask = (flown.t >= off + result.tau_stream) & (flown.t <= off + final.t_end)
        flown_enu = swap_points(flown.pos[mask])
        flown_tau = flown.t[mask] - off
    path_png = r.out / f"{name}_path.png"
    rep.plot_path(path_png, title, scene, planned, flown_enu, flown_tau, result.tau_stream)
    deriv_png = r.out / f"{name}_derivatives.png"
    rep.plot_derivatives(deriv_png, f"{title}: derivatives against bounds", result.trajectories,
                         result.starts, result.bounds, flown,
                         None if result.tracking is None else result.tracking.offset, result.tau_stream)
    return [path_png, deriv_png]


# --- main ------------------------------------------------------------------------------------


def fly_transit(r: Rig, mission: dict[str, Any], here: np.ndarray | None, timeout: float,
                progress: Progress) -> str | None:
    """Fly the transit legs onto the mission's waypoint 0; the reason if one failed."""
    for leg in transit(mission, here):
        for _ in range(3):
            moved = fly(r, leg, [], timeout, progress)
            # a machine busy elsewhere can make a plan miss its split time: try again
            if moved.ok or "split time" not in moved.reason:
                break
        if not moved.ok:
            return moved.reason
    return None


def _quick_mission() -> dict[str, Any]:
    return {
        "id": "quick",
        "frame": "enu",
        "origin": "home",
        "start": "current",
        "waypoints": [[2.0, 1.0, LIFT + 0.5], [4.0, 3.0, LIFT + 1.0]],
        "bounds": {"velocity": 3, "acceleration": 3, "jerk": 10, "snap": 50},
    }


def keep_recording(recordings: Path, flight: Path) -> Path | None:
    """The companion's recording of this run (the newest file it wrote) as `flight`."""
    files = sorted(recordings.glob("*.mcap"), key=lambda p: p.stat().st_mtime)
    if not files:
        return None
    files[-1].replace(flight)
    return flight


def build_parser(prog: str = "python -m demo") -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog=prog, description=__doc__.splitlines()[0].split(": ", 1)[-1])
    p.add_argument("--autopilot", choices=["px4", "ardupilot"], default="px4")
    p.add_argument("--out", type=Path, default=Path("out/demo"))
    p.add_argument("--quick", action="store_true", help="one short mission only (smoke test)")
    p.add_argument("--fleet", type=int, metavar="N", default=0,
                   help="the fleet demo instead: one router, N mocks and companions, crossing missions (demo.fleet)")
    p.add_argument("--timeout", type=float, default=120.0, help="per mission, seconds")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("--no-limits", action="store_true",
                   help="do not read the autopilot's speed and acceleration limits (plan at the configured bounds "
                        "only; docs/autopilot-limits.md): to compare the tracking with and without them")
    p.add_argument("--no-recording", action="store_true",
                   help="do not have the companion record the flight (out/demo/flight.mcap)")
    p.add_argument("--lead", type=_lead, default="auto", metavar="SECONDS|auto",
                   help="sample setpoints this far ahead of the plan (companion [setpoints] lead; 0: off; "
                        "auto, the default: the lag estimated in flight)")
    return p


def _lead(text: str) -> float | str:
    return "auto" if text == "auto" else float(text)


def main(argv: list[str] | None = None, prog: str = "python -m demo") -> int:
    args = build_parser(prog).parse_args(argv)
    out: Path = args.out
    if args.fleet:
        from demo.fleet import run as run_fleet

        if args.fleet < 2:
            print("--fleet: at least 2 vehicles", file=sys.stderr)
            return 2
        try:
            return run_fleet(args.fleet, out.parent / "fleet" if out == Path("out/demo") else out,
                             plots=not args.no_plots)
        except (RuntimeError, OSError) as exc:
            print(f"fleet demo failed: {exc}", file=sys.stderr)
            return 1
    progress = Progress()
    results: list[rep.MissionResult] = []
    pngs: list[Path] = []
    print(f"bezier-companion demo: mock {args.autopilot} autopilot + companion service + Zenoh peer")
    try:
        recordings = out / "recordings"
        with rig(out, args.autopilot, lead=args.lead, recording=None if args.no_recording else recordings,
                 read_limits=not args.no_limits) as r:
            print(f"  companion pid {r.companion.pid}, mock pid {r.mock.pid}, logs in {out}/")
            print("  waiting for the autopilot to be ready (a valid home)", flush=True)
            home = r.wait_home()
            print(f"  home (the ground where the vehicle stands) at local NED {home.round(2).tolist()}: "
                  "the demo's missions and the positions it prints are ENU from home")
            to_sim = sim_clock(r)
            plans: list[tuple[str, str, dict[str, Any], list[Action], dict[str, Any] | None, dict[str, Any] | None]] = []
            if args.quick:
                plans.append(("quick", "Quick mission", _quick_mission(), [], None, None))
            else:
                s1 = lifted_mission(load_example("scenario1.json"), "scenario1")
                s2 = lifted_mission(load_example("scenario2.json"), "scenario2")
                popup = lifted_obstacles(clear_of_route(load_example("scenario2_popup.json"), s2,
                                                        r.config.planner.tracking_allowance))
                change = lifted_change(load_example("scenario2_move.json"))
                acts = [Action(after(1.5), "change", change, "waypoint move"),
                        Action(after(3.0), "obstacles", popup, "pop-up obstacle")]
                plans.append(("scenario1", "Scenario 1 (paper), lifted 2 m", s1, [], None, None))
                plans.append(("scenario2", "Scenario 2 (paper): waypoint 2 moved, pop-up obstacle",
                              s2, acts, popup, change))
            here: np.ndarray | None = None  # on the ground
            for name, title, mission, actions, popup_msg, change_msg in plans:
                if mission.get("start") == "first_waypoint":
                    print(f"- transit to {name}'s waypoint 0 (over the obstacles)")
                    failed = fly_transit(r, mission, here, args.timeout, progress)
                    if failed:
                        results.append(rep.MissionResult(name=name, ok=False, reason=f"transit: {failed}"))
                        break
                print(f"- {title}: {len(mission['waypoints'])} waypoints")
                outcome = fly(r, mission, actions, args.timeout, progress)
                here = np.asarray(mission["waypoints"][-1], dtype=float)
                result = analyse(name, mission, outcome, r, to_sim,
                                 lead=0.0 if args.lead == "auto" else float(args.lead))
                results.append(result)
                if not args.no_plots:
                    pngs += figures(name, title, mission, result, r, popup_msg, change_msg)
                print(f"  {name}: {'OK' if result.ok else 'FAILED: ' + result.reason}", flush=True)
                if not result.ok and not outcome.trajectories:
                    break
    except (RuntimeError, OSError) as exc:
        print(f"demo failed: {exc}", file=sys.stderr)
        return 1
    if not args.no_recording:
        flight = keep_recording(recordings, out / "flight.mcap")
        if flight is not None:
            print(f"\nflight recording: {flight} ({flight.stat().st_size / 1e6:.1f} MB)\n"
                  f"  python -m companion recording summary {flight}\n"
                  f"  python -m companion replay {flight}\n"
                  "  Foxglove (app.foxglove.dev or the desktop app): Open local file, then a 3D panel "
                  "(display frame local_enu) and a Plot panel (docs/recording.md)")
            if not args.no_plots:
                from demo.recording_plots import plot

                png = plot(flight, out / "flight_recording.png")
                if png is not None:
                    pngs.append(png)
    print()
    print(rep.format_table(results))
    if pngs:
        print("\nfigures: " + ", ".join(str(p) for p in pngs))
    summary = {"ok": bool(results) and all(x.ok for x in results),
               "missions": [dict(rep.summary_rows(x)) for x in results]}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return 0 if summary["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
