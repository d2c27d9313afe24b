"""`python -m demo` (or `python -m companion demo`): the whole chain on this machine, no hardware.

Starts the mock autopilot (sitl_mock) and the companion service as subprocesses on free loopback
ports, joins their Zenoh network as a peer, and flies the paper's two scenarios in real time:
scenario 1, then scenario 2 with a pop-up obstacle published mid-flight and a waypoint moved out
of its way. It prints live progress and a summary table, writes figures to out/demo/, and exits
non-zero if a mission was not flown as planned. Here: the scenarios and the run; the flights
are demo.flying, their analysis and figures demo.analysis, the processes demo.rig.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import Any

import numpy as np

from companion.config import tracking_allowance
from demo import report as rep
from demo.analysis import analyse, figures, sim_clock
from demo.flying import Action, Progress, after, fly
from demo.rig import ROOT, TAKEOFF_ALTITUDE, Rig, rig

EXAMPLES = ROOT / "examples"
UP = np.array([0.0, 0.0, 1.0])  # ENU
# m: the paper's scenarios touch z = 0; fly them this much higher (ENU, up), which is also where
# the companion's takeoff leaves the vehicle
LIFT = TAKEOFF_ALTITUDE


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
    p.add_argument("--autopilot-url", metavar="URL",
                   help="fly a running autopilot (PX4 or ArduPilot SITL, say which with --autopilot) at this "
                        "MAVLink URL instead of starting the mock: udpin:HOST:PORT (PX4 SITL: "
                        "udpin:127.0.0.1:14540), udpout:, tcp: (ArduPilot SITL: tcp:127.0.0.1:5760) or tcpin:. "
                        "The tracking figures are then against the autopilot's own position estimate")
    p.add_argument("--out", type=Path, default=Path("out/demo"))
    p.add_argument("--quick", action="store_true", help="one short mission only (smoke test)")
    p.add_argument("--fleet", type=int, metavar="N", default=0,
                   help="the fleet demo instead: one router, N mocks and companions, crossing missions (demo.fleet)")
    p.add_argument("--timeout", type=float, default=120.0, help="per mission, seconds")
    p.add_argument("--no-plots", action="store_true")
    p.add_argument("--set", action="append", default=[], metavar="SECTION.KEY=VALUE", dest="settings",
                   help="change the companion's config for this run (repeatable), e.g. autopilot_limits.headroom=0.6")
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
    if args.fleet and args.autopilot_url:
        print("--fleet flies mocks only: not with --autopilot-url", file=sys.stderr)
        return 2
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
    url = args.autopilot_url
    where = f"{args.autopilot} autopilot at {url}" if url else f"mock {args.autopilot} autopilot"
    print(f"bezier-companion demo: {where} + companion service + Zenoh peer")
    try:
        recordings = out / "recordings"
        with rig(out, args.autopilot, lead=args.lead, recording=None if args.no_recording else recordings,
                 read_limits=not args.no_limits, autopilot_url=url, settings=args.settings) as r:
            print(f"  companion pid {r.companion.pid}, {r.mock.name} pid {r.mock.pid}, logs in {out}/")
            if url:
                print("  tracking is measured against the autopilot's own position estimate (LOCAL_POSITION_NED), "
                      "not the truth; against the truth too where the autopilot sends it (HIL_STATE_QUATERNION)")
            print("  waiting for the autopilot to be ready (a valid home)", flush=True)
            # PX4 SITL is ready ~40 s after boot, ArduCopter SITL reports a position ~60 s after
            home = r.wait_home(90.0 if url is None else 300.0)
            print(f"  home (the ground where the vehicle stands) at local NED {home.round(2).tolist()}: "
                  "the demo's missions and the positions it prints are ENU from home")
            # the tap logs on this machine's monotonic clock; the mock on its simulated one
            to_sim = (lambda mono: mono) if url else sim_clock(r)
            plans: list[tuple[str, str, dict[str, Any], list[Action], dict[str, Any] | None, dict[str, Any] | None]] = []
            if args.quick:
                plans.append(("quick", "Quick mission", _quick_mission(), [], None, None))
            else:
                s1 = lifted_mission(load_example("scenario1.json"), "scenario1")
                s2 = lifted_mission(load_example("scenario2.json"), "scenario2")
                popup = lifted_obstacles(clear_of_route(load_example("scenario2_popup.json"), s2,
                                                        tracking_allowance(r.config.planner, args.autopilot)[0]))
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
                r.refresh_home()  # what the mission's "origin": "home" is resolved against
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
    except (RuntimeError, OSError, ValueError) as exc:
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
               "missions": [dict(rep.summary_rows(x)) for x in results],
               "tracking": {x.name: rep.tracking_record(x) for x in results}}
    (out / "summary.json").write_text(json.dumps(summary, indent=2))
    return 0 if summary["ok"] else 1


if __name__ == "__main__":
    sys.exit(main())
