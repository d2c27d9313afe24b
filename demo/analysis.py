"""The demo's analysis of a flight: the plans published, the flight log (the mock's, or with an
external autopilot the demo's tap's, demo.tap) and the companion's events turned into a
`report.MissionResult` (latencies, tracking error, peaks against bounds), and its figures.
"""

from __future__ import annotations

import contextlib
import json
import math
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from companion.lag import initial_aim, initial_aim_horizontal
from companion.wire.frames import swap_points
from demo import report as rep
from demo.flying import FlightOutcome
from demo.rig import Rig, Sample
from planner_core import Trajectory

MAX_TRACKING_ERROR = 1.0  # m: beyond this the flight is not "as planned"
EARTH_RADIUS = 6371000.0  # m, as PX4's map projection (lib/geo)


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


def read_truth(log: Path) -> rep.Flown | None:
    """An external autopilot's ground truth (the tap's "truth" records, PX4 SIH's
    HIL_STATE_QUATERNION) in its local NED frame, placed by its home (the last HOME_POSITION
    logged: where it is globally and in the local frame); None without either. Over a few
    hundred metres the local tangent plane is exact to millimetres."""
    truth: list[dict[str, Any]] = []
    home: dict[str, Any] | None = None
    with open(log, encoding="utf-8") as fh:
        for line in fh:
            if '"truth"' in line or '"home"' in line:
                rec = json.loads(line)
                if rec.get("type") == "truth":
                    truth.append(rec)
                elif rec.get("type") == "home":
                    home = rec
    if home is None or len(truth) < 10:
        return None
    lat0, lon0 = math.radians(home["lat"]), math.radians(home["lon"])
    lat = np.radians([r["lat"] for r in truth])
    lon = np.radians([r["lon"] for r in truth])
    pos = np.stack([(lat - lat0) * EARTH_RADIUS, (lon - lon0) * EARTH_RADIUS * math.cos(lat0),
                    -(np.array([r["alt"] for r in truth], float) - float(home["alt"]))], axis=1)
    return rep.Flown(np.array([r["t"] for r in truth], float), pos + np.asarray(home["pos"], float),
                     np.array([r["vel"] for r in truth], float))


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
    time.sleep(0.7)  # the mock flushes its log every 0.5 s (the tap every 0.2 s)
    flown, sp_t, sp_p, sp_c = read_flown_sent(r.flight_log)
    if len(sp_t) < 10 or len(flown.t) < 10:
        result.ok, result.reason = False, "the flight log has no applied setpoints"
        return result
    s_stream = mono_to_sim(outcome.t_stream if outcome.t_stream is not None else outcome.t_put)
    s_first_change = mono_to_sim(samples[1].mono) if len(samples) > 1 else (
        mono_to_sim(outcome.t_done) if outcome.t_done is not None else s_stream + first.t_end - first.t0)
    window = (sp_t >= s_stream) & (sp_t <= s_first_change)
    if window.sum() < 10:
        window = sp_t >= s_stream
    # the setpoints are points of the plan, or with [setpoints] accel_lead k of p + k p''
    k_acc, tc_acc = initial_aim(r.config.setpoints.accel_lead, r.config.setpoints.accel_lead_tc, r.autopilot)
    aim_h = initial_aim_horizontal(r.config.setpoints.aim_horizontal, r.autopilot)
    offset = rep.align_offset(first, sp_t[window], sp_p[window], s_stream - first.t_end, s_stream - first.t0, k_acc,
                              tc_acc, aim_h)
    starts = replan_starts(samples, outcome.events, mono_to_sim, offset)
    tau_end = (mono_to_sim(outcome.t_done) - offset) if outcome.t_done is not None else final.t_end
    flying = (sp_t >= s_stream) & (sp_t <= offset + tau_end)
    if flying.sum() < 10:
        result.ok, result.reason = False, "no setpoints of this mission in the flight log"
        return result
    sp_t, sp_p, sp_c = sp_t[flying], sp_p[flying], sp_c[flying]
    # (an auto lead moves the setpoints up to [setpoints] lead_max along the plan in flight)
    sp_raw, sp_off = rep.local_offsets(result.trajectories, starts, sp_t, sp_p, offset, search=0.6,
                                         accel_lead=k_acc, accel_lead_tc=tc_acc, aim_horizontal=aim_h)
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
    # each flown sample against the plan at its own time, for fitting an aim (docs/autopilot-limits.md)
    np.savetxt(r.out / f"{name}_tracking.csv", result.tracking.samples, delimiter=",", fmt="%.5f",
               header="tau_s,err_n,err_e,err_d,plan_vn,plan_ve,plan_vd,plan_an,plan_ae,plan_ad")
    if r.external:
        # the tap's states are what the autopilot believes (LOCAL_POSITION_NED), not the truth
        result.tracked = "the autopilot's estimate"
        truth = read_truth(r.flight_log)
        if truth is not None:
            result.tracking_truth = rep.tracking_error(result.trajectories, starts, truth, sp_t, sp_off,
                                                       result.tau_stream, tau_end)
    # every setpoint the mock received must be a point of the planned trajectory (float32 on
    # the wire): checks frames, splicing and sampling end to end
    dev = np.linalg.norm(sp_p - rep.aimed(result.trajectories, starts, sp_t - sp_raw, k_acc, tc_acc, aim_h), axis=1)
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
    rep.plot_path(path_png, title, scene, planned, flown_enu, flown_tau, result.tau_stream,
                  "flown (autopilot's estimate)" if r.external else "flown (mock log)")
    deriv_png = r.out / f"{name}_derivatives.png"
    rep.plot_derivatives(deriv_png, f"{title}: derivatives against bounds", result.trajectories,
                         result.starts, result.bounds, flown,
                         None if result.tracking is None else result.tracking.offset, result.tau_stream)
    return [path_png, deriv_png]
