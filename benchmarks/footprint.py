"""Footprint benchmark: whole-process start-up and first plan of the CLI, where the compiled pass
pays off, and the companion service's total resident memory idle and while planning.

1. CLI: `python -m planner_core plan SCENARIO -o OUT --json` as a whole process, several runs,
   medians: wall time from the parent (interpreter start to exit), the CLI's own split (start-up:
   imports and loading the compiled pass; plan: planning and verifying), the path taken and the
   peak RSS. "cold" runs point NUMBA_CACHE_DIR at an empty directory (a fresh install: the
   compiled pass, if used, compiles first); "warm" runs use the checkout's cache.
2. Crossover: one plan in-process on the compiled pass and on the numpy + daqp path by the number
   of waypoints, and the cost of loading the compiled pass (a fresh process, warm cache), which
   is what planner_core.iterative.KERNEL_MIN_WAYPOINTS is chosen from.
3. Planner process alone: a fresh process (as a companion planner worker: numpy + daqp path, numba
   never loaded; on the compiled pass from numba's JIT, its cache warm; on the compiled pass's AOT
   build, `python -m planner_core.build_kernel`, no numba) plans a chain scenario with obstacles of
   1000 and 2000 waypoints; the time to load the build (import, then a 4-waypoint warm-up plan: the
   JIT loads its cached code at each function's first call), its resident memory after loading,
   its peak during the first plan (VmHWM, reset before the plan) and after it, the plan's time
   (first, and best of two more) and the peak of Python-level allocations (tracemalloc, numpy
   arrays included; a fourth plan).
4. Service: the real companion against the mock autopilot (demo.rig, as benchmarks/service.py),
   every process it starts summed (RSS, and PSS, which splits shared pages among the processes
   sharing them): idle = up, warmed up and linked, no mission; planning = flying the benchmark's
   lap mission while it checks 1000-waypoint missions back to back (the load of
   benchmarks/service.py); per planner layout (`--layouts`; see LAYOUTS and companion/runtime.py).

Targets: CLI first plan of a 10-waypoint scenario <= 0.5 s wall; service total <= 250 MB idle,
<= 300 MB planning. Timings are noisy on a shared machine.

    python benchmarks/footprint.py [--runs 5] [--skip-cli] [--skip-crossover] [--skip-planner] [--skip-service]
        [--planner-sizes 1000 2000] [--planner-paths numpy jit aot]
        [--layouts default compiled-workers thread] [--json out/bench/footprint.json]
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import importlib.util
import itertools
import json
import os
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
TARGETS = {"cli_10wp_wall_s": 0.5, "service_idle_mb": 250.0, "service_planning_mb": 300.0}


# --- scenarios -----------------------------------------------------------------------------------


def chain_scenario(m: int, seed: int = 3, obstacles: bool = True) -> dict[str, Any]:
    """m waypoints on a random walk (ENU, 1.5-3 m up), box obstacles (A, b) beside the legs,
    well clear of them, and durations from 2 m/s: a scenario the CLI builds corridors for."""
    rng = np.random.default_rng(seed)
    steps = rng.normal(size=(m - 1, 3)) * [3.0, 3.0, 0.3]
    wps = np.cumsum(np.vstack([[0.0, 0.0, 2.0], steps]), axis=0)
    wps[:, 2] = np.clip(wps[:, 2], 1.5, 3.0)
    lengths = np.linalg.norm(np.diff(wps, axis=0), axis=1)
    out: dict[str, Any] = {
        "description": f"footprint benchmark: {m} waypoints" + (", box obstacles" if obstacles else ""),
        "frame": "enu", "waypoints": wps.round(3).tolist(),
        "durations": np.maximum(lengths / 2.0, 1.0).round(3).tolist(),
        "bounds": {"velocity": 5, "acceleration": 4, "jerk": 12, "snap": 40},
        "vehicle_radius": 0.3,
    }
    if obstacles:
        eye = np.eye(3)
        boxes = []
        for a, b in itertools.pairwise(wps):
            d = b - a
            side = np.cross(d, [0.0, 0.0, 1.0])
            side /= max(float(np.linalg.norm(side)), 1e-9)
            c = 0.5 * (a + b) + 2.5 * side  # 2.5 m beside the leg's middle, 0.4 m half-size
            if _leg_distance(c, wps) < 2.0:  # the walk came back near it: leave this one out
                continue
            boxes.append({"A": np.vstack([eye, -eye]).tolist(),
                          "b": np.concatenate([c + 0.4, -(c - 0.4)]).round(4).tolist()})
        out["obstacles"] = boxes
    return out


def _leg_distance(point: np.ndarray, wps: np.ndarray) -> float:
    a, d = wps[:-1], np.diff(wps, axis=0)
    u = np.clip(np.einsum("ij,ij->i", point - a, d) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0.0, 1.0)
    return float(np.min(np.linalg.norm(point - (a + u[:, None] * d), axis=1)))


# --- 1. the CLI as a whole process ------------------------------------------------------------------


def _run_cli(scenario: Path, out: Path, env: dict[str, str], extra: tuple[str, ...] = ()) -> dict[str, Any]:
    with tempfile.TemporaryFile("w+") as fo, tempfile.TemporaryFile("w+") as fe:
        t0 = time.perf_counter()
        proc = subprocess.Popen([sys.executable, "-m", "planner_core", "plan", str(scenario), "-o", str(out),
                                 "--json", *extra], cwd=ROOT, env=env, stdout=fo, stderr=fe)
        # wait4: this child's own peak RSS (RUSAGE_CHILDREN would be the max over all children)
        _, status, usage = os.wait4(proc.pid, 0)
        wall = time.perf_counter() - t0
        proc.returncode = os.waitstatus_to_exitcode(status)
        fo.seek(0)
        fe.seek(0)
        stdout, stderr = fo.read(), fe.read()
    if proc.returncode != 0:
        raise RuntimeError(f"planner_core plan {scenario.name} failed ({proc.returncode}): {stderr[-2000:]}")
    summary = json.loads(stdout.strip().splitlines()[-1])
    return {"wall_s": wall, "plan_s": summary["plan_s"], "scenario_s": summary["scenario_s"],
            "startup_s": summary["startup"]["total_s"],
            "imports_s": summary["startup"]["imports_s"], "kernel_load_s": summary["startup"]["kernel_load_s"],
            "path": summary["startup"]["path"], "max_rss_mb": usage.ru_maxrss / 1024,  # KB on Linux
            "compile_note": "compiling" in stderr}


def cli_rows(runs: int) -> list[dict[str, Any]]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp_dir:
        tmp = Path(tmp_dir)
        cases = [("examples/scenario1.json (8 wp, vertex obstacles)", ROOT / "examples" / "scenario1.json", ()),
                 ("10 wp, box obstacles", tmp / "chain10.json", ()),
                 ("10 wp, --compiled on", tmp / "chain10.json", ("--compiled", "on")),
                 ("2000 wp, no obstacles", tmp / "chain2000.json", ())]
        (tmp / "chain10.json").write_text(json.dumps(chain_scenario(10)))
        (tmp / "chain2000.json").write_text(json.dumps(chain_scenario(2000, obstacles=False)))
        for label, path, extra in cases:
            for cache in ("warm", "cold"):
                env = dict(os.environ)
                n = runs
                if cache == "cold":
                    env["NUMBA_CACHE_DIR"] = tempfile.mkdtemp(dir=tmp)  # empty: what a fresh install has
                    n = 1  # a cold run of the compiled path compiles for ~20 s
                samples = [_run_cli(path, tmp / "out.json", env, extra) for _ in range(n)]
                if cache == "cold" and samples[0]["path"] == "numpy":
                    samples += [_run_cli(path, tmp / "out.json", env, extra) for _ in range(runs - 1)]
                row: dict[str, Any] = {"case": label, "cache": cache, "runs": len(samples),
                                       "path": samples[0]["path"],
                                       "compile_note": any(s["compile_note"] for s in samples)}
                for key in ("wall_s", "startup_s", "imports_s", "kernel_load_s", "scenario_s", "plan_s", "max_rss_mb"):
                    row[key] = statistics.median(s[key] for s in samples)
                rows.append(row)
                print(f"  cli: {label}, {cache} cache: wall {row['wall_s']:.3f} s", flush=True)
    return rows


# --- 2. where the compiled pass pays off ----------------------------------------------------------


def crossover_rows(sizes: tuple[int, ...] = (10, 100, 300, 1000, 2000)) -> tuple[list[dict[str, Any]], float]:
    code = ("import time\nimport planner_core.iterative as it\nt = time.perf_counter()\nit.warm_up()\n"
            "print(time.perf_counter() - t)")
    loads = [float(subprocess.run([sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True,
                                  check=True).stdout.split()[-1]) for _ in range(3)]
    from planner_core.formats.io import load_scenario
    from planner_core.iterative import IterativeOptions, plan_iterative, warm_up

    warm_up()
    rows = []
    for m in sizes:
        problem = load_scenario(chain_scenario(m, obstacles=False)).problem
        row: dict[str, Any] = {"waypoints": m}
        for name, compiled in (("compiled_s", True), ("numpy_s", False)):
            times = []
            for _ in range(3):
                res = plan_iterative(problem, IterativeOptions(compiled=compiled))
                times.append(res.stats["time_total"])
            row[name] = min(times)
            row["recoveries"] = len(res.stats.get("recoveries", []))
        rows.append(row)
        print(f"  crossover: m = {m}: compiled {row['compiled_s']:.4f} s, numpy {row['numpy_s']:.4f} s", flush=True)
    return rows, statistics.median(loads)


# --- 3. one planner process's memory ---------------------------------------------------------------

_PLANNER_PROBE = """
import json, os, sys, time, tracemalloc
from pathlib import Path
path = sys.argv[2]
compiled = path != "numpy"
if not compiled:
    from planner_core import use_compiled_kernel
    use_compiled_kernel(False, "footprint benchmark: numpy path")
from planner_core.formats.io import load_scenario
from planner_core.iterative import IterativeOptions, plan_iterative, warm_up
from planner_core.window import aot_unavailable, kernel_kind
def kb(key):
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return float(line.split()[1]) / 1024
problem = load_scenario(json.loads(Path(sys.argv[1]).read_text())).problem
rss_start = kb("VmRSS")
t_load = time.perf_counter()
kind = kernel_kind()  # imports the build: numba's JIT (window_kernel) or the AOT module
t_imported = time.perf_counter()
warm_up()  # a 4-waypoint plan: the JIT loads its cached machine code at a function's first call
t_warm = time.perf_counter()
opts = IterativeOptions(compiled=compiled)
before = kb("VmRSS")
Path("/proc/self/clear_refs").write_text("5")  # VmHWM := VmRSS: the peak of what follows
t0 = time.perf_counter()
res = plan_iterative(problem, opts)
seconds = time.perf_counter() - t0
hwm = kb("VmHWM")
after = kb("VmRSS")
again = []
for _ in range(2):
    t0 = time.perf_counter()
    plan_iterative(problem, opts)
    again.append(time.perf_counter() - t0)
tracemalloc.start()
plan_iterative(problem, opts)
traced = tracemalloc.get_traced_memory()[1] / 2**20
print(json.dumps({"ok": res.ok, "plan_s": seconds, "plan_again_s": min(again),
                  "recoveries": len(res.stats.get("recoveries", [])),
                  "compiled_steps": res.stats["n_compiled_steps"], "kernel": kind or "none",
                  "aot_unavailable": aot_unavailable() if compiled else None,
                  "kernel_import_s": t_imported - t_load, "kernel_load_s": t_warm - t_load,
                  "rss_start_mb": rss_start, "rss_before_mb": before, "hwm_mb": hwm, "rss_after_mb": after,
                  "traced_peak_mb": traced, "numba": "numba" in sys.modules}))
"""

# planner process paths: the numpy + daqp path (use_compiled_kernel(False), as the companion's
# planner processes), the compiled pass from numba's JIT (its on-disk cache warm) and its AOT
# build (python -m planner_core.build_kernel); "compiled": whichever the process picks (auto)
PLANNER_PATHS = {"numpy": "auto", "jit": "jit", "aot": "aot", "compiled": "auto"}


def planner_rows(sizes: tuple[int, ...] = (1000, 2000), paths: tuple[str, ...] = ("numpy", "jit", "aot")
                 ) -> list[dict[str, Any]]:
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        for m in sizes:
            scenario = Path(tmp) / f"chain_{m}.json"
            scenario.write_text(json.dumps(chain_scenario(m)))
            for path in paths:
                env = dict(os.environ, PLANNER_CORE_KERNEL=PLANNER_PATHS[path])
                out = subprocess.run([sys.executable, "-c", _PLANNER_PROBE, str(scenario), path], cwd=ROOT,
                                     capture_output=True, text=True, check=True, env=env)
                row: dict[str, Any] = {"waypoints": m, "path": path, **json.loads(out.stdout.splitlines()[-1])}
                row["plan_peak_mb"] = row["hwm_mb"] - row["rss_before_mb"]
                rows.append(row)
                print(f"  planner: m = {m}, {path} ({row['kernel']}): load {row['kernel_load_s']:.3f} s, plan "
                      f"{row['plan_s']:.3f} s, RSS {row['rss_before_mb']:.0f} MB loaded, peak {row['hwm_mb']:.0f} MB "
                      f"(+{row['plan_peak_mb']:.1f} MB for the plan)", flush=True)
    return rows


# --- 4. the service's memory ------------------------------------------------------------------------


LAYOUTS: dict[str, dict[str, Any]] = {
    "default": {},  # as shipped: see companion/runtime.py
    "compiled-workers": {"compiled": True, "urgent": "process"},  # the layout before: two numba workers
    "thread": {"executor": "thread"},  # missions in a thread of the service
}


def _kb(path: str, key: str) -> float:
    with contextlib.suppress(OSError):
        for line in Path(path).read_text().splitlines():
            if line.startswith(key + ":"):
                return float(line.split()[1])
    return 0.0


def tree_peaks(pid: int) -> tuple[float, float]:
    """Peak resident memory (VmHWM, MB) of pid itself, and the largest among its descendants
    (the planner worker: the other child, multiprocessing's resource tracker, stays ~13 MB)."""
    procs = _service_bench()._tree(pid)  # pid and its descendants
    own = _kb(f"/proc/{pid}/status", "VmHWM") / 1024
    children = [_kb(f"/proc/{p}/status", "VmHWM") / 1024 for p in procs if p != pid]
    return own, max(children, default=0.0)


def tree_memory(pid: int) -> tuple[float, float, int]:
    """(RSS sum, PSS sum) in MB over pid and its descendants, and how many processes."""
    procs = _service_bench()._tree(pid)  # pid and its descendants
    rss = sum(_kb(f"/proc/{p}/status", "VmRSS") for p in procs) / 1024
    pss = sum(_kb(f"/proc/{p}/smaps_rollup", "Pss") for p in procs) / 1024
    return rss, pss, len(procs)


@contextlib.contextmanager
def _layout(overrides: dict[str, Any]) -> Iterator[None]:
    from demo import rig as demo_rig

    original = demo_rig.demo_config

    def config(*args: Any, **kwargs: Any) -> Any:
        cfg = original(*args, **kwargs)
        return dataclasses.replace(cfg, planner=dataclasses.replace(cfg.planner, **overrides))

    demo_rig.demo_config = config  # type: ignore[assignment]
    try:
        yield
    finally:
        demo_rig.demo_config = original  # type: ignore[assignment]


@functools.cache
@functools.cache
def _service_bench() -> Any:
    spec = importlib.util.spec_from_file_location("service_bench", Path(__file__).with_name("service.py"))
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["service_bench"] = module  # its dataclasses look their module up
    spec.loader.exec_module(module)
    return module


def service_row(name: str, out: Path, idle_s: float = 4.0, plans: int = 4) -> dict[str, Any]:
    from demo.rig import rig

    bench = _service_bench()
    row: dict[str, Any] = {"layout": name, **LAYOUTS[name]}
    with _layout(LAYOUTS[name]), rig(out / name, "px4") as r:
        pid = r.companion.pid
        time.sleep(1.0)  # the warm-up plans have run before `rig` returns; let the heap settle
        idle = []
        deadline = time.monotonic() + idle_s
        while time.monotonic() < deadline:
            idle.append(tree_memory(pid))
            time.sleep(0.1)
        samples: list[tuple[float, float, int]] = []
        stop = threading.Event()

        def sample() -> None:
            while not stop.is_set():
                samples.append(tree_memory(pid))
                time.sleep(0.05)

        events = bench._EventLog(r.peer)
        # fly (a 1000-waypoint mission is checked against where the vehicle is), then load
        t_put = r.peer.put("mission", bench.flight_mission())
        events.wait(lambda e: e.get("type") == "accepted" and e.get("key") == "mission", t_put, 30.0)
        r.peer.put("command", {"command": "start"})
        if events.wait(lambda e: e.get("type") == "state" and e.get("to") == "STREAMING", t_put, 60.0) is None:
            raise RuntimeError("the companion never started streaming\n" + r.companion.tail())
        sampler = threading.Thread(target=sample, daemon=True)
        sampler.start()
        mission = bench.big_mission()
        times, verdicts = [], []
        for _ in range(plans):
            t0 = r.peer.put("mission", mission)
            done = events.wait(lambda e: e.get("key") == "mission" and e.get("type") in ("accepted", "rejected")
                               and "bench-1000" in str(e.get("message", "")), t0, 120.0)
            if done is None:
                break
            times.append(done - t0)
            with events._lock:
                verdicts.append(next(ev.get("type") for m, ev in reversed(events.items) if m == done))
        time.sleep(1.0)
        stop.set()
        sampler.join()
        after = tree_memory(pid)
        service_peak, worker_peak = tree_peaks(pid)
    row.update({
        "service_hwm_mb": service_peak, "worker_hwm_mb": worker_peak,
        "processes": max(s[2] for s in idle),
        "idle_rss_mb": max(s[0] for s in idle), "idle_pss_mb": max(s[1] for s in idle),
        "planning_rss_mb": max(s[0] for s in samples) if samples else float("nan"),
        "planning_pss_mb": max(s[1] for s in samples) if samples else float("nan"),
        "after_rss_mb": after[0], "after_pss_mb": after[1],
        "plans_1000": len(times), "plan_1000_median_s": statistics.median(times) if times else float("nan"),
        "plans_1000_accepted": verdicts.count("accepted"),
    })
    print(f"  service [{name}]: idle {row['idle_rss_mb']:.0f} MB RSS / {row['idle_pss_mb']:.0f} MB PSS, planning "
          f"{row['planning_rss_mb']:.0f} / {row['planning_pss_mb']:.0f} MB", flush=True)
    return row


# --- tables -----------------------------------------------------------------------------------------


def table(rows: list[dict[str, Any]], columns: list[tuple[str, str, str]]) -> str:
    head = [c[0] for c in columns]
    body = [[fmt.format(r.get(key, float("nan"))) for _, key, fmt in columns] for r in rows]
    return str(_service_bench().grid(head, body))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--runs", type=int, default=5, help="CLI runs per case (medians)")
    p.add_argument("--skip-cli", action="store_true")
    p.add_argument("--skip-crossover", action="store_true")
    p.add_argument("--skip-planner", action="store_true")
    p.add_argument("--planner-sizes", type=int, nargs="+", default=[1000, 2000], help="waypoints, section 3")
    p.add_argument("--planner-paths", nargs="+", choices=sorted(PLANNER_PATHS), default=["numpy", "jit", "aot"],
                   help="section 3: numpy + daqp, the compiled pass's JIT build or its AOT build")
    p.add_argument("--skip-service", action="store_true")
    p.add_argument("--layouts", nargs="+", choices=sorted(LAYOUTS), default=["default", "compiled-workers"])
    p.add_argument("--plans", type=int, default=4, help="1000-waypoint missions planned per layout")
    p.add_argument("--out", type=Path, default=Path("out/bench/footprint"))
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    report: dict[str, Any] = {"targets": TARGETS}
    if not args.skip_cli:
        print("CLI runs ...", flush=True)
        report["cli"] = cli_rows(args.runs)
    if not args.skip_crossover:
        print("crossover ...", flush=True)
        report["crossover"], report["kernel_load_s"] = crossover_rows()
    if not args.skip_planner:
        print("planner process ...", flush=True)
        report["planner"] = planner_rows(tuple(args.planner_sizes), tuple(args.planner_paths))
    if not args.skip_service:
        print("service ...", flush=True)
        report["service"] = [service_row(name, args.out, plans=args.plans) for name in args.layouts]
    if "cli" in report:
        print("\n`python -m planner_core plan` as a whole process (medians; wall <= 0.5 s for 10 waypoints)")
        print(table(report["cli"], [
            ("case", "case", "{}"), ("cache", "cache", "{}"), ("runs", "runs", "{}"), ("path", "path", "{}"),
            ("wall [s]", "wall_s", "{:.3f}"), ("start-up [s]", "startup_s", "{:.3f}"),
            ("  imports [s]", "imports_s", "{:.3f}"), ("  compiled pass [s]", "kernel_load_s", "{:.3f}"),
            ("scenario + corridors [s]", "scenario_s", "{:.3f}"), ("plan [s]", "plan_s", "{:.4f}"),
            ("max RSS [MB]", "max_rss_mb", "{:.0f}"),
            ("compile note", "compile_note", "{}")]))
    if "crossover" in report:
        print(f"\none plan in-process, compiled pass vs numpy + daqp path (best of 3); loading the compiled "
              f"pass in a fresh process: {report['kernel_load_s']:.3f} s")
        print(table(report["crossover"], [
            ("waypoints", "waypoints", "{}"), ("compiled [s]", "compiled_s", "{:.4f}"),
            ("numpy [s]", "numpy_s", "{:.4f}"), ("recoveries", "recoveries", "{}")]))
    if "planner" in report:
        print("\none planner process planning a chain scenario with obstacles (load: importing the build and a "
              "4-waypoint warm-up plan; RSS loaded: after it; peak: VmHWM during the first plan)")
        print(table(report["planner"], [
            ("waypoints", "waypoints", "{}"), ("path", "path", "{}"), ("kernel", "kernel", "{}"),
            ("numba loaded", "numba", "{}"), ("import [s]", "kernel_import_s", "{:.3f}"),
            ("load [s]", "kernel_load_s", "{:.3f}"), ("plan [s]", "plan_s", "{:.3f}"),
            ("plan again [s]", "plan_again_s", "{:.3f}"), ("compiled steps", "compiled_steps", "{}"),
            ("recoveries", "recoveries", "{}"), ("RSS start [MB]", "rss_start_mb", "{:.1f}"),
            ("RSS loaded [MB]", "rss_before_mb", "{:.1f}"), ("peak RSS [MB]", "hwm_mb", "{:.1f}"),
            ("RSS after [MB]", "rss_after_mb", "{:.1f}"), ("plan's share [MB]", "plan_peak_mb", "{:.1f}"),
            ("traced peak [MB]", "traced_peak_mb", "{:.1f}")]))
    if "service" in report:
        print("\ncompanion service, every process summed (<= 250 MB idle, <= 300 MB planning)")
        print(table(report["service"], [
            ("layout", "layout", "{}"), ("processes", "processes", "{}"),
            ("idle RSS [MB]", "idle_rss_mb", "{:.0f}"), ("idle PSS [MB]", "idle_pss_mb", "{:.0f}"),
            ("planning RSS [MB]", "planning_rss_mb", "{:.0f}"), ("planning PSS [MB]", "planning_pss_mb", "{:.0f}"),
            ("after RSS [MB]", "after_rss_mb", "{:.0f}"), ("service peak [MB]", "service_hwm_mb", "{:.0f}"),
            ("worker peak [MB]", "worker_hwm_mb", "{:.0f}"), ("1000-wp plans", "plans_1000", "{}"),
            ("  accepted", "plans_1000_accepted", "{}"),
            ("1000-wp plan median [s]", "plan_1000_median_s", "{:.2f}")]))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(report, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
