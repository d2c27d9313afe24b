"""Numbers and figures for `python -m demo`: tracking, peaks, tables, plots.

Pure functions over arrays (no Zenoh, no processes) so they can be checked on their own.
Frames: the flight log and the trajectories are NED; figures are drawn in ENU (z up) like the
paper's scenarios.
"""

from __future__ import annotations

import itertools
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from companion.wire.frames import swap_halfspaces, swap_points
from planner_core import Trajectory

if TYPE_CHECKING:
    from companion.setpoints import AimTerms

FloatArray = NDArray[np.float64]

ORDER_LABELS = ("velocity [m/s]", "acceleration [m/s²]", "jerk [m/s³]", "snap [m/s⁴]")
AXES = ("x", "y", "z")


@dataclass
class Flown:
    """Vehicle states from the mock's flight log on the mock's clock (NED)."""

    t: FloatArray
    pos: FloatArray
    vel: FloatArray


@dataclass
class Tracking:
    offset: float  # flight log clock time of trajectory time 0
    rms: float
    max: float
    n: int
    span: tuple[float, float] = (float("nan"), float("nan"))  # trajectory times measured over
    # per flown sample: trajectory time, then the plan minus the flown position, the plan's
    # velocity and acceleration there (m, m/s, m/s², local NED), shape (n, 10)
    samples: FloatArray = field(default_factory=lambda: np.zeros((0, 10)))


@dataclass
class MissionResult:
    name: str
    ok: bool = False
    reason: str = ""
    plan_latency: float | None = None  # mission put -> streaming it (s; includes takeoff if any)
    plan_ms: float | None = None  # the companion's own plan + verify time
    replan_ms: list[float] = field(default_factory=list)
    message_to_setpoint_ms: list[float] = field(default_factory=list)
    setpoint_deviation: float | None = None  # max |setpoint at the mock - planned| (m)
    starts: list[float] = field(default_factory=list)
    tau_stream: float = -float("inf")  # trajectory time at which this mission took over
    replan_latencies: dict[str, float] = field(default_factory=dict)
    stats: dict[str, Any] = field(default_factory=dict)
    flight_time: float | None = None
    tracking: Tracking | None = None
    # what `tracking` measured: the mock's truth, or an external autopilot's own estimate
    tracked: str = "the mock's vehicle"
    tracking_truth: Tracking | None = None  # an external autopilot's ground truth, where it sends it
    # s, per applied setpoint: how far ahead of its own time it was sampled (the lead)
    leads: FloatArray | None = None
    peaks_planned: FloatArray | None = None  # (4, 3) max |derivative| per axis
    peaks_flown: FloatArray | None = None  # (2, 3) velocity, acceleration
    bounds: FloatArray | None = None  # (4, 3) symmetric magnitude per axis (NED)
    trajectories: list[Trajectory] = field(default_factory=list)


# --- geometry --------------------------------------------------------------------------------


def polytope_vertices(A: FloatArray, b: FloatArray, tol: float = 1e-7) -> FloatArray:
    """Vertices of a bounded {x : A x <= b} by enumerating plane triples (small polytopes)."""
    A = np.asarray(A, dtype=float)
    b = np.asarray(b, dtype=float)
    triples = np.array(list(itertools.combinations(range(len(b)), 3)))
    if len(triples) == 0:
        return np.zeros((0, 3))
    mats = A[triples]
    ok = np.abs(np.linalg.det(mats)) > 1e-12
    pts = np.linalg.solve(mats[ok], b[triples[ok]][..., None])[..., 0]
    inside = np.all(pts @ A.T <= b + tol * (1 + np.abs(b)), axis=1)
    return np.unique(np.round(pts[inside], 9), axis=0)


def hull2d(points: FloatArray) -> FloatArray:
    """Convex hull of 2-D points, counter-clockwise (Andrew's monotone chain)."""
    pts = sorted(set(map(tuple, np.round(np.asarray(points, dtype=float), 9))))
    if len(pts) < 3:
        return np.array(pts, dtype=float).reshape(-1, 2)

    def half(seq: Sequence[tuple[float, float]]) -> list[tuple[float, float]]:
        out: list[tuple[float, float]] = []
        for p in seq:
            while len(out) >= 2 and (
                (out[-1][0] - out[-2][0]) * (p[1] - out[-2][1])
                - (out[-1][1] - out[-2][1]) * (p[0] - out[-2][0])
            ) <= 0:
                out.pop()
            out.append(p)
        return out

    lower, upper = half(pts), half(pts[::-1])
    return np.array(lower[:-1] + upper[:-1], dtype=float)


def region_vertices_enu(region: dict[str, Any], frame: str) -> FloatArray:
    """Vertices (ENU) of an obstacle/corridor given as {"vertices"} or {"A","b"}."""
    if "vertices" in region:
        pts = np.asarray(region["vertices"], dtype=float)
        return pts if frame == "enu" else swap_points(pts)
    A = np.asarray(region["A"], dtype=float)
    if frame != "enu":
        A = swap_halfspaces(A)
    return polytope_vertices(A, np.asarray(region["b"], dtype=float))


# --- tracking and peaks ----------------------------------------------------------------------


def align_offset(traj: Trajectory, t: FloatArray, pos: FloatArray, lo: float, hi: float,
                 accel_lead: float = 0.0, accel_lead_tc: float = 0.0, aim_horizontal: AimTerms = ()) -> float:
    """Mock-clock time of trajectory time 0 that best matches the commanded positions.

    The setpoints the mock logged are samples of the trajectory, so the right offset makes them
    coincide; a scan of [lo, hi] then a golden-section refine finds it without trusting the two
    processes to share an epoch.
    """
    if len(t) > 400:
        idx = np.linspace(0, len(t) - 1, 400).astype(int)
        t, pos = t[idx], pos[idx]

    def cost(off: float) -> float:
        d = aimed([traj], [-np.inf], t - off, accel_lead, accel_lead_tc, aim_horizontal) - pos
        return float(np.mean(np.sum(d * d, axis=1)))

    grid = np.linspace(lo, hi, int(min(max((hi - lo) / 0.05, 20), 2000)))
    costs = [cost(g) for g in grid]
    k = int(np.argmin(costs))
    step = float(grid[1] - grid[0])
    a, b = float(grid[k]) - step, float(grid[k]) + step
    ratio = (np.sqrt(5) - 1) / 2
    for _ in range(50):
        c, d = b - ratio * (b - a), a + ratio * (b - a)
        if cost(c) < cost(d):
            b = d
        else:
            a = c
    return (a + b) / 2


def stitched(trajs: Sequence[Trajectory], starts: Sequence[float], tau: FloatArray, order: int = 0) -> FloatArray:
    """Position at trajectory times tau from whichever trajectory was active then.

    starts[k] is the trajectory time from which trajectory k was the active one (a replan equals
    its predecessor up to its split point, so taking it over a little late changes nothing).
    """
    which = np.clip(np.searchsorted(np.asarray(starts), tau, side="right") - 1, 0, len(trajs) - 1)
    out = np.empty((len(tau), 3))
    for k in np.unique(which):
        sel = which == k
        out[sel] = trajs[int(k)].evaluate(tau[sel], order)
    return out


def aimed(trajs: Sequence[Trajectory], starts: Sequence[float], tau: FloatArray, accel_lead: float = 0.0,
          accel_lead_tc: float = 0.0, aim_horizontal: AimTerms = ()) -> FloatArray:
    """What the setpoints of trajectory times tau aimed at: the plan's position, plus
    `[setpoints] accel_lead` times its acceleration, low-passed with `accel_lead_tc`
    (companion.setpoints.sample), and the horizontal aim's terms `aim_horizontal`."""
    out = stitched(trajs, starts, tau)
    for k, tc in aim_horizontal:
        grid, f = _filtered_accel(tuple(trajs), tuple(float(x) for x in starts), tc)
        out[:, :2] += k * np.stack([np.interp(tau, grid, f[:, c]) for c in range(2)], axis=1)
    if not accel_lead:
        return out
    if accel_lead_tc <= 0.0:
        return out + accel_lead * stitched(trajs, starts, tau, 2)
    grid, f = _filtered_accel(tuple(trajs), tuple(float(x) for x in starts), accel_lead_tc)
    return out + accel_lead * np.stack([np.interp(tau, grid, f[:, c]) for c in range(3)], axis=1)


_FILTERED: dict[tuple[Any, ...], tuple[FloatArray, FloatArray, tuple[Trajectory, ...]]] = {}


def _filtered_accel(trajs: tuple[Trajectory, ...], starts: tuple[float, ...], tc: float) -> tuple[FloatArray, FloatArray]:
    """The stitched plan's acceleration low-passed as companion.setpoints.filtered_accel does,
    on a 10 ms grid over the whole plan and the filter's tail after it (computed once)."""
    key = (tuple(id(t) for t in trajs), starts, tc)
    if key not in _FILTERED:
        from companion.setpoints import FILTER_SPAN, filter_weights

        lags, w = filter_weights(tc)
        t0, t_end = trajs[0].t0, trajs[-1].t_end
        grid = np.arange(t0 - 0.02, t_end + FILTER_SPAN * tc + 0.02, 0.01)
        times = (grid[:, None] - lags[None, :]).ravel()
        acc = stitched(trajs, starts, np.clip(times, t0, t_end), 2)
        acc[times >= t_end] = 0.0
        f = np.einsum("j,ijc->ic", w, acc.reshape(len(grid), len(lags), 3))
        if any(k[:2] != key[:2] for k in _FILTERED):
            _FILTERED.clear()  # one flight at a time: keep the trajectories alive no longer than that
        _FILTERED[key] = (grid, f, trajs)  # (holding trajs keeps their ids from being reused)
    grid, f, _ = _FILTERED[key]
    return grid, f


def local_offsets(trajs: Sequence[Trajectory], starts: Sequence[float], t: FloatArray, pos: FloatArray,
                  offset: float, search: float = 0.3, step: float = 0.002,
                  smooth: int = 51, accel_lead: float = 0.0, accel_lead_tc: float = 0.0,
                  aim_horizontal: AimTerms = ()) -> tuple[FloatArray, FloatArray]:
    """Mock-clock time of trajectory time 0, per setpoint, smoothed.

    The mock's simulated clock slips against wall time when the machine is busy (it catches up
    at most a few steps at a time), so one global offset would read a scheduling hiccup as
    tracking error. Each setpoint is matched to the nearest planned point within +-search s of
    the global estimate; a running median removes the ambiguity of hovering stretches.
    Returns (raw, smoothed) offsets. `accel_lead`: the setpoints aimed beyond the plan (`aimed`).
    """
    grid = np.arange(-search, search + step / 2, step)
    tau = (t - offset)[:, None] + grid[None, :]
    pts = aimed(trajs, starts, tau.ravel(), accel_lead, accel_lead_tc, aim_horizontal).reshape(len(t), len(grid), 3)
    best = grid[np.argmin(np.sum((pts - pos[:, None, :]) ** 2, axis=2), axis=1)]
    # refine to 0.05 ms around the coarse match: the deviation check wants ~1e-5 m resolution
    fine = np.linspace(-step, step, 81)
    tau = (t - offset + best)[:, None] + fine[None, :]
    pts = aimed(trajs, starts, tau.ravel(), accel_lead, accel_lead_tc, aim_horizontal).reshape(len(t), len(fine), 3)
    best = best + fine[np.argmin(np.sum((pts - pos[:, None, :]) ** 2, axis=2), axis=1)]
    raw = offset - best
    half = smooth // 2
    padded = np.pad(raw, half, mode="edge")
    windows = np.lib.stride_tricks.sliding_window_view(padded, smooth)
    return raw, np.asarray(np.median(windows, axis=1), dtype=float)


def running_median(values: FloatArray, window: int = 51) -> FloatArray:
    """`values` smoothed by a running median (edges padded): a send stamp's millisecond
    resolution must not read as a change of the lead."""
    v = np.asarray(values, dtype=float)
    if len(v) == 0:
        return v
    half = window // 2
    windows = np.lib.stride_tricks.sliding_window_view(np.pad(v, half, mode="edge"), window)
    return np.asarray(np.median(windows, axis=1), dtype=float)


def tracking_error(trajs: Sequence[Trajectory], starts: Sequence[float], flown: Flown,
                   sp_t: FloatArray, sp_offsets: FloatArray, tau_start: float, tau_end: float) -> Tracking:
    """Flown position against the planned one, from the first mission trajectory to tau_end (m)."""
    offsets = np.interp(flown.t, sp_t, sp_offsets)
    tau = flown.t - offsets
    span = (max(tau_start, trajs[0].t0), min(tau_end, trajs[-1].t_end))
    mask = (tau >= span[0]) & (tau <= span[1])
    if not mask.any():
        return Tracking(float(np.median(sp_offsets)), float("nan"), float("nan"), 0, span)
    diff = stitched(trajs, starts, tau[mask]) - flown.pos[mask]
    err = np.linalg.norm(diff, axis=1)
    samples = np.column_stack([tau[mask], diff, stitched(trajs, starts, tau[mask], 1),
                               stitched(trajs, starts, tau[mask], 2)])
    return Tracking(float(np.median(sp_offsets)), float(np.sqrt(np.mean(err**2))), float(err.max()),
                    int(mask.sum()), span, samples)


def planned_peaks(traj: Trajectory, samples_per_segment: int = 400) -> FloatArray:
    """Max |d^k/dt^k| per axis for k = 1..4, sampled densely, shape (4, 3), from where the plan
    begins (stats `spliced_at`: the pieces before it were flown under the previous plan, such as a
    transit at the companion's bounds, not this mission's)."""
    t = _sample_times(traj, samples_per_segment)
    t = t[t >= float(traj.stats.get("spliced_at", -np.inf)) - 1e-9]
    return np.array([np.abs(traj.evaluate(t, k)).max(axis=0) for k in range(1, 5)])


def flown_peaks(flown: Flown, t0: float, t1: float) -> FloatArray:
    """Max |velocity| and |acceleration| per axis of the flown states in [t0, t1], shape (2, 3)."""
    mask = (flown.t >= t0) & (flown.t <= t1)
    if mask.sum() < 3:
        return np.full((2, 3), np.nan)
    t, vel = flown.t[mask], flown.vel[mask]
    acc = np.gradient(vel, t, axis=0)
    return np.array([np.abs(vel).max(axis=0), np.abs(acc).max(axis=0)])


def _sample_times(traj: Trajectory, per_segment: int) -> FloatArray:
    u = np.linspace(0.0, 1.0, per_segment)
    return np.unique(np.concatenate([t0 + u * (t1 - t0) for t0, t1 in itertools.pairwise(traj.times)]))


def bounds_matrix(bounds: dict[str, Any] | None, frame: str) -> FloatArray | None:
    """Symmetric per-axis magnitude (4, 3) in NED from a scenario "bounds" object."""
    if not bounds:
        return None
    rows = []
    for name in ("velocity", "acceleration", "jerk", "snap"):
        value = bounds.get(name)
        if value is None:
            rows.append(np.full(3, np.inf))
        elif isinstance(value, int | float):
            rows.append(np.full(3, float(value)))
        elif len(value) == 2 and all(isinstance(v, int | float) for v in value):
            rows.append(np.full(3, max(abs(value[0]), abs(value[1]))))
        else:
            per_axis = np.array([max(abs(lo), abs(hi)) for lo, hi in value])
            rows.append(per_axis[[1, 0, 2]] if frame == "enu" else per_axis)
    return np.array(rows)


# --- table -----------------------------------------------------------------------------------


def _ms(x: float | None) -> str:
    return "-" if x is None else f"{1e3 * x:.1f} ms"


def _us(x: float | None) -> str:
    return "-" if x is None else f"{1e6 * x:.0f} µs"


def _peak(peaks: FloatArray | None, bounds: FloatArray | None, row: int) -> str:
    if peaks is None:
        return "-"
    value = float(np.nanmax(peaks[row]))
    if bounds is None or not np.isfinite(bounds[row]).any():
        return f"{value:.2f}"
    return f"{value:.2f} / {float(np.min(bounds[row])):.2f}"


def _short(text: str, n: int = 60) -> str:
    line = text.splitlines()[0] if text else ""
    return line if len(line) <= n else line[: n - 3] + "..."


def _ms_list(values: Sequence[float]) -> str:
    return "-" if not values else ", ".join(f"{v:.1f}" for v in values) + " ms"


def summary_rows(result: MissionResult) -> list[tuple[str, str]]:
    st = result.stats
    rows = [
        ("result", "OK" if result.ok else f"FAILED: {_short(result.reason)}"),
        ("plan + verify (companion)", "-" if result.plan_ms is None else f"{result.plan_ms:.1f} ms"),
        ("window QPs / median step", f"{st.get('n_qp', '-')} / {_us(_num(st.get('step_time_median')))}"),
        ("verified", str(st.get("verified", "-"))),
        ("mission put -> streaming", "-" if result.plan_latency is None else f"{result.plan_latency:.2f} s"),
    ]
    for what, latency in result.replan_latencies.items():
        rows.append((f"{what}: put -> new trajectory", _ms(latency)))
    rows.append(("replans (companion, each)", _ms_list(result.replan_ms)))
    rows.append(("message -> first new setpoint", _ms_list(result.message_to_setpoint_ms)))
    rows.append(("flight time", "-" if result.flight_time is None else f"{result.flight_time:.1f} s"))
    if result.tracking is not None:
        rows.append(("tracking error RMS / max", f"{result.tracking.rms:.3f} / {result.tracking.max:.3f} m"))
        rows.append(("tracking measured on", result.tracked))
    if result.tracking_truth is not None:
        rows.append(("tracking vs truth RMS / max",
                     f"{result.tracking_truth.rms:.3f} / {result.tracking_truth.max:.3f} m"))
    if result.leads is not None and len(result.leads):
        # the flight is compared with the plan at its own time: each setpoint's lead taken off
        rows.append(("setpoint lead, first / last", f"{result.leads[0] * 1000:.0f} / {result.leads[-1] * 1000:.0f} ms"))
    if result.setpoint_deviation is not None:
        rows.append(("setpoints vs trajectory, max", f"{result.setpoint_deviation:.1e} m"))
    b = result.bounds
    rows += [
        ("peak |v| planned / bound", _peak(result.peaks_planned, b, 0)),
        ("peak |a| planned / bound", _peak(result.peaks_planned, b, 1)),
        ("peak |j| planned / bound", _peak(result.peaks_planned, b, 2)),
        ("peak |s| planned / bound", _peak(result.peaks_planned, b, 3)),
        ("peak |v| flown / bound", _peak(result.peaks_flown, b, 0)),
        ("peak |a| flown / bound", _peak(result.peaks_flown, b, 1)),
    ]
    return rows


def _num(x: Any) -> float | None:
    return float(x) if isinstance(x, int | float) else None


def tracking_record(result: MissionResult) -> dict[str, Any] | None:
    """The tracking figures as numbers (summary.json), with what a check needs to redo them:
    the flight log clock's time of trajectory time 0, the trajectory times measured over and
    each replan's start (the plans are in NAME_trajectories.json)."""
    tr = result.tracking
    if tr is None:
        return None
    truth = result.tracking_truth
    return {"rms": tr.rms, "max": tr.max, "n": tr.n, "measured_on": result.tracked, "offset": tr.offset,
            "span": list(tr.span), "starts": [float(s) if np.isfinite(s) else None for s in result.starts],
            "truth": None if truth is None else {"rms": truth.rms, "max": truth.max, "n": truth.n}}


def format_table(results: Sequence[MissionResult]) -> str:
    names = [r.name for r in results]
    per = [dict(summary_rows(r)) for r in results]
    keys: list[str] = []
    for r in results:
        keys += [k for k, _ in summary_rows(r) if k not in keys]
    cols = [[k, *[p.get(k, "") for p in per]] for k in keys]
    head = ["", *names]
    widths = [max(len(head[i]), *(len(c[i]) for c in cols)) for i in range(len(head))]
    line = "-+-".join("-" * w for w in widths)
    fmt = " | ".join(f"{{:{'<' if i == 0 else '>'}{w}}}" for i, w in enumerate(widths))
    return "\n".join([fmt.format(*head), line, *(fmt.format(*c) for c in cols)])


# --- figures ---------------------------------------------------------------------------------


@dataclass
class Scene:
    """What a path figure draws, all in ENU."""

    waypoints: FloatArray
    obstacles: list[FloatArray] = field(default_factory=list)
    popups: list[FloatArray] = field(default_factory=list)
    corridors: list[FloatArray] = field(default_factory=list)
    moved: list[tuple[FloatArray, FloatArray]] = field(default_factory=list)


def plot_path(
    path: Path,
    title: str,
    scene: Scene,
    planned: Sequence[tuple[str, Trajectory]],
    flown_enu: FloatArray | None,
    flown_tau: FloatArray | None = None,
    tau_start: float = -np.inf,
    flown_label: str = "flown (mock log)",
) -> None:
    """Top view with obstacles and corridors, and altitude against trajectory time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (top, side) = plt.subplots(1, 2, figsize=(14, 5.6), gridspec_kw={"width_ratios": [1.4, 1]})
    t_zero = tau_start if np.isfinite(tau_start) else planned[0][1].t0
    for verts in scene.corridors:
        if len(verts) >= 3:
            h = hull2d(verts[:, :2])
            top.fill(h[:, 0], h[:, 1], facecolor="tab:green", alpha=0.05, edgecolor="tab:green",
                     lw=0.7, label="corridors")
    for verts, color, name in [(v, "0.4", "obstacle") for v in scene.obstacles] + [
        (v, "tab:red", "pop-up obstacle") for v in scene.popups
    ]:
        if len(verts) >= 3:
            h = hull2d(verts[:, :2])
            top.fill(h[:, 0], h[:, 1], facecolor=color, alpha=0.6, edgecolor=color, label=name)
    colors = ["tab:blue", "tab:purple"]
    for k, (label, traj) in enumerate(planned):
        last = k == len(planned) - 1
        t = _sample_times(traj, 200)
        t = t[t >= tau_start]
        pts = swap_points(traj.evaluate(t))
        style = {"color": colors[min(k, 1)], "lw": 2.2 if last else 1.3, "alpha": 1.0 if last else 0.55,
                 "ls": "-" if last else "-.", "label": label}
        top.plot(pts[:, 0], pts[:, 1], **style)
        side.plot(t - t_zero, pts[:, 2], **style)
    if flown_enu is not None and len(flown_enu):
        top.plot(flown_enu[:, 0], flown_enu[:, 1], "--", color="tab:orange", lw=1.5, label=flown_label)
        if flown_tau is not None:
            side.plot(flown_tau - t_zero, flown_enu[:, 2], "--", color="tab:orange", lw=1.5, label=flown_label)
    wp = scene.waypoints
    top.plot(wp[:, 0], wp[:, 1], "o", ms=6, mfc="white", mec="k", label="waypoints", zorder=5)
    for i, p in enumerate(wp):
        top.annotate(str(i), (p[0], p[1]), textcoords="offset points", xytext=(5, 5), fontsize=8)
    for old, new in scene.moved:
        top.annotate("", xy=(new[0], new[1]), xytext=(old[0], old[1]),
                     arrowprops={"arrowstyle": "->", "color": "tab:red", "lw": 1.5})
        top.plot([new[0]], [new[1]], "s", color="tab:red", ms=6, label="moved waypoint", zorder=5)
    lo, hi = _extent(scene, planned, flown_enu, tau_start)
    top.set_xlim(lo[0], hi[0])
    top.set_ylim(lo[1], hi[1])
    top.set_xlabel("east x [m]")
    top.set_ylabel("north y [m]")
    top.set_aspect("equal", adjustable="box")
    top.grid(True, alpha=0.3)
    top.set_title("top view")
    side.set_xlabel("mission time [s]")
    side.set_ylabel("altitude z (up) [m]")
    side.grid(True, alpha=0.3)
    side.set_title("altitude")
    handles, names = top.get_legend_handles_labels()
    unique = dict(zip(names, handles, strict=True))
    fig.legend(unique.values(), unique.keys(), loc="lower center", ncol=min(len(unique), 8), frameon=False)
    fig.suptitle(title)
    fig.tight_layout(rect=(0, 0.07, 1, 0.96))
    fig.savefig(path, dpi=110)
    plt.close(fig)


def _extent(scene: Scene, planned: Sequence[tuple[str, Trajectory]], flown: FloatArray | None,
            tau_start: float, margin: float = 1.5) -> tuple[FloatArray, FloatArray]:
    """What is worth looking at: paths, waypoints and obstacles (corridors may reach the map edge)."""
    pts = [scene.waypoints, *scene.obstacles, *scene.popups]
    for _, tr in planned:
        t = _sample_times(tr, 50)
        pts.append(swap_points(tr.evaluate(t[t >= tau_start])))
    if flown is not None and len(flown):
        pts.append(flown)
    allp = np.vstack([p for p in pts if len(p)])
    return allp.min(axis=0) - margin, allp.max(axis=0) + margin


def plot_derivatives(
    path: Path,
    title: str,
    trajs: Sequence[Trajectory],
    starts: Sequence[float],
    bounds: FloatArray | None,
    flown: Flown | None,
    offset: float | None,
    tau_start: float = -np.inf,
) -> None:
    """Velocity..snap of the flown plan (stitched across replans) against the bounds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    starts = list(starts) if len(starts) == len(trajs) else [-np.inf] * len(trajs)
    t = np.unique(np.concatenate([_sample_times(tr, 300) for tr in trajs]))
    t = t[(t >= max(trajs[0].t0, tau_start)) & (t <= trajs[-1].t_end)]
    t_zero = float(t[0])
    fig, axes = plt.subplots(4, 1, figsize=(11, 9), sharex=True)
    colors = ("tab:blue", "tab:orange", "tab:green")
    for k, ax in enumerate(axes, start=1):
        values = swap_points(stitched(trajs, starts, t, k))
        for a in range(3):
            ax.plot(t - t_zero, values[:, a], color=colors[a], lw=1.3, label=f"planned {AXES[a]} (ENU)")
        if bounds is not None and np.isfinite(bounds[k - 1]).any():
            b = float(np.min(bounds[k - 1]))
            for sign in (-1, 1):
                ax.axhline(sign * b, color="k", ls="--", lw=1.0, label="bound" if sign > 0 else None)
        for s in starts[1:]:
            if s < t[0]:
                continue
            ax.axvline(s - t_zero, color="tab:red", lw=0.8, alpha=0.6, label="replan" if s == starts[1] else None)
        if k == 1 and flown is not None and offset is not None:
            mask = (flown.t - offset >= t[0]) & (flown.t - offset <= t[-1])
            vel = swap_points(flown.vel[mask])
            for a in range(3):
                ax.plot(flown.t[mask] - offset - t_zero, vel[:, a], ":", color=colors[a], lw=1.4, label=f"flown {AXES[a]}")
        ax.set_ylabel(ORDER_LABELS[k - 1])
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="upper right", ncol=4, fontsize=8)
    axes[-1].set_xlabel("mission time [s]")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
