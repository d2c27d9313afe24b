"""Flight recorder cost, without a flight: what a setpoint send pays for being recorded, and the
writer thread's CPU for a minute of flight traffic.

1. A SET_POSITION_TARGET_LOCAL_NED encoded and written by pymavlink (to memory), as the
   setpoint thread does, without and with the recorder's send callback (a `put_nowait`; its
   writer thread recording to a file meanwhile).
2. The writer thread's conversions (JSON, MAVLink to dict, Foxglove 3D messages, MCAP chunks)
   for the records of one minute of flight at the mock PX4's rates: 50 Hz setpoints, 30 Hz
   LOCAL_POSITION_NED, 10 Hz ATTITUDE, 20 Hz telemetry, 2 Hz status, and one plan.

3. The autopilot watch's rules on the loop (companion.autopilot_rules.watch_step through
   AutopilotWatch, as each LOCAL_POSITION_NED and link check calls them), without and with the
   recorder's observer, and the writer thread's conversion of one /autopilot/step record.

4. The tracking error's rules on the loop (companion.tracking_rules.tracking_step through
   Tracking.check_tracking, as each LOCAL_POSITION_NED calls it, a plan of ours flown), without
   and with the recorder's observer; the writer thread's conversion of one /tracking/step
   record, its bytes (JSON, and zstd-compressed in a minute's run of them), and what the 30 Hz
   of them add to a minute's file.

benchmarks/service.py --recording-only measures the same recorder in a real flight (setpoint
jitter at the relay, CPU, memory), which a loaded machine makes noisy.

    python benchmarks/recorder.py [--sends 5000] [--json out/bench/recorder.json]
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests" / "companion"))


def send_cost(sends: int, record: bool, every: float = 0.002) -> dict[str, float]:
    """Sends `every` s apart (the writer thread, recording to a file, runs in between, as in the
    service), automatic garbage collection off (the service paces it: companion.runtime.GcPacer)."""
    import gc

    from recorder_support import Wire, config

    from companion.recorder import Recorder

    with tempfile.TemporaryDirectory() as d:
        rec = Recorder(config(d)) if record else None
        if rec is not None:
            rec.open()
        wire = Wire(rec.mavlink_sent if rec is not None else None)
        times = np.empty(sends)
        gc.collect()
        gc.disable()
        try:
            for k in range(sends):
                t0 = time.perf_counter()
                wire.setpoint(k)
                times[k] = time.perf_counter() - t0
                wire.buf.clear()
                time.sleep(every)
        finally:
            gc.enable()
            if rec is not None:
                rec.close()
    us = times * 1e6
    return {"median_us": float(np.median(us)), "p99_us": float(np.percentile(us, 99)), "max_us": float(us.max())}


def tracking_items(seconds: float, rate: float = 30.0) -> list[tuple[Any, ...]]:
    """A minute of /tracking/step records as the service queues them while a plan is flown: an
    error per position sample (noisy, as measured), the window of the last 150 behind it."""
    from companion.tracking_rules import TrackingRules, TrackingSample, TrackingState, tracking_step

    rng = np.random.default_rng(1)
    ts, items = TrackingState(), []
    for k in range(int(seconds * rate)):
        reading = TrackingSample(float(abs(rng.normal(0.05, 0.03))), True, True, 0.3,
                                 "[planner] tracking_allowance (PX4's default)", 0.3, False)
        after, outs = tracking_step(TrackingRules(), ts, reading)
        items.append(("tracking_step", k + 1, 40, ts, reading, after, outs, k / rate))
        ts = after
    return items


def writer_cost(seconds: float = 60.0, tracking: bool = True) -> dict[str, float]:
    """`tracking`: with the /tracking/step records of the same minute (30 Hz)."""
    from recorder_support import Wire, config, plan_call

    from companion.recorder import Recorder

    with tempfile.TemporaryDirectory() as d:
        rec = Recorder(config(d))
        rec.open()
        rec._stop.set()  # the thread ends at once: conversions are driven and timed here
        assert rec._thread is not None
        rec._thread.join()
        w = Wire()
        items: list[tuple[Any, ...]] = []
        for k in range(int(seconds * 50)):
            t = k / 50
            items.append(("mavlink_sent", w.tx.set_position_target_local_ned_encode(
                k, 1, 1, 1, 2048, 0.1, 0, -1, 0, 0, 0, 0, 0, 0, 0, 0), t))
            if k % 5 < 3:
                items.append(("mavlink_received", w.received(w.tx.local_position_ned_encode(k, 0.01 * k, 0, -1, 0, 0, 0)), t))
            if k % 5 == 0:
                items.append(("mavlink_received", w.received(w.tx.attitude_encode(k, 0, 0, 0.5, 0, 0, 0)), t))
            if k % 5 < 2:
                items.append(("outbound", "telemetry", json.dumps({
                    "time": t, "frame": "ned", "position": [1, 2, 3], "velocity": [0, 0, 0],
                    "attitude": {"roll": 0, "pitch": 0, "yaw": 0}, "armed": True, "mode": "OFFBOARD"}).encode(), t))
            if k % 25 == 0:
                items.append(("outbound", "status", json.dumps({"state": "STREAMING", "n": k}).encode(), t))
        if tracking:
            items += tracking_items(seconds)
            items.sort(key=lambda it: it[-1] if it[0] != "tracking_step" else it[7])
        fn, args, out = plan_call(rec.cfg)
        items.append(("plan", fn, args, out, 1.0, 1.2, "process"))
        assert out.route is not None
        items.append(("flown", out.route.trajectory, 0.0, 1.2))
        t0 = time.process_time()
        for it in items:
            rec._convert(it)
        took = time.process_time() - t0
        rec.close()
        size = sum(p.stat().st_size for p in Path(d).glob("*.mcap"))
    return {"records": float(len(items)), "cpu_s": took, "core_percent": 100.0 * took / seconds,
            "file_kb": size / 1024}


def watch_cost(calls: int, record: bool) -> dict[str, float]:
    """AutopilotWatch calls back to back: a position of a vehicle flying (armed, 2 m above the
    ground it learnt, no landed state: the height rule runs to its end) and a link check (heard),
    alternately, as the service's telemetry arrives; with `record`, the supervisor and the watch
    connected to a Recorder writing a file, as the service connects them."""
    from recorder_support import config

    from companion.autopilot import AutopilotWatch
    from companion.flight import FlightState, State
    from companion.recorder import Recorder
    from companion.report import Reporter
    from companion.supervisor import Supervisor
    from companion.wire.vehicle import VehicleState

    class Link:
        state = VehicleState(autopilot="px4", armed=True, mode="OFFBOARD")

    with tempfile.TemporaryDirectory() as d:
        sup = Supervisor(FlightState(State.STREAMING, True, seen_link=True, ground_z=0.0))
        link = Link()
        watch = AutopilotWatch(config(d), sup, link, Reporter(sup))  # type: ignore[arg-type]
        rec = Recorder(config(d)) if record else None
        if rec is not None:
            rec.open()
            sup.connect(observe=rec.transition)
            watch.connect(observe=rec.autopilot_step)
        st = link.state
        st.position, st.velocity = np.array([1.0, 2.0, -2.0]), np.array([0.5, 0.0, 0.0])

        def one(k: int) -> float:
            now = time.monotonic()
            st.last_heartbeat = st.last_message = now
            t0 = time.perf_counter()
            if k % 2:
                watch.check_link()
            else:
                watch.on_position(now)
            return time.perf_counter() - t0

        return _timed(calls, one, rec)


def _timed(calls: int, one: Callable[[int], float], rec: Any = None) -> dict[str, float]:
    """`one(k)` (which returns the seconds it timed) for k < `calls`, automatic garbage collection
    off (the service paces it), 2 ms off every 500 calls: the writer thread takes what was
    queued, as between loop steps; then `rec` (a Recorder) closed."""
    import gc

    times = np.empty(calls)
    gc.collect()
    gc.disable()
    try:
        for k in range(calls):
            times[k] = one(k)
            if k % 500 == 0:
                time.sleep(0.002)
    finally:
        gc.enable()
        if rec is not None:
            rec.close()
    us = times * 1e6
    return {"median_us": float(np.median(us)), "p99_us": float(np.percentile(us, 99)), "max_us": float(us.max())}


def tracking_cost(calls: int, record: bool) -> dict[str, float]:
    """Tracking.check_tracking calls back to back while a plan of ours is flown (the error
    scripted, under the limit: the rules run to their end, the window full; no lag estimate),
    with `record` the rules' observer a Recorder writing a file, as the service connects it."""
    from recorder_support import BrakingNavigator, ScriptedControl, TrackingLink, config

    from companion.flight import FlightState, State
    from companion.recorder import Recorder
    from companion.report import Reporter
    from companion.supervisor import Supervisor
    from companion.tracking import Tracking

    with tempfile.TemporaryDirectory() as d:
        cfg = config(d)
        cfg = replace(cfg, planner=replace(cfg.planner, tracking_allowance=0.3))
        sup = Supervisor(FlightState(State.STREAMING, True, seen_link=True, ground_z=0.0))
        control = ScriptedControl()
        tracking = Tracking(cfg, sup, control, TrackingLink(), BrakingNavigator(sup), Reporter(sup))  # type: ignore[arg-type]
        rec = Recorder(cfg) if record else None
        if rec is not None:
            rec.open()
            tracking.connect(observe=rec.tracking_step)
        rng = np.random.default_rng(1)
        errors = np.abs(rng.normal(0.05, 0.03, calls))

        def one(k: int) -> float:
            control.error = float(errors[k])
            now = time.monotonic()
            t0 = time.perf_counter()
            tracking.check_tracking(now)
            return time.perf_counter() - t0

        return _timed(calls, one, rec)


def tracking_record_cost(seconds: float = 60.0) -> dict[str, float]:
    """The writer's conversion of a /tracking/step record (us of CPU), its JSON bytes, and its
    bytes zstd-compressed among a minute of them (as the file's chunks compress them)."""
    import zstandard

    from companion.record_bodies import tracking_record

    items = tracking_items(seconds)
    t0 = time.process_time()
    data = [tracking_record(seq, first, t, before, reading, after, outs, False)
            for _kind, seq, first, before, reading, after, outs, t in items]
    took = (time.process_time() - t0) / len(items) * 1e6
    packed = len(zstandard.ZstdCompressor().compress(b"".join(data)))
    return {"convert_us": took, "json_bytes": sum(map(len, data)) / len(data), "zstd_bytes": packed / len(data)}


def step_record_cost(records: int = 3000) -> float:
    """The writer thread's conversion of an /autopilot/step record (JSON, pickle), in us."""
    from companion.autopilot_rules import PositionSeen, WatchRules, WatchState, watch_step
    from companion.flight import FlightState, State
    from companion.record_bodies import step_record

    fs = FlightState(State.STREAMING, True, seen_link=True, ground_z=0.0)
    ws = WatchState()
    reading = PositionSeen(1.0, 2.0, -2.0, 0.5, 0.0, 0.0, True, -np.inf, 1, 1)
    after, outs = watch_step(WatchRules(), ws, fs, reading, 100.0)
    t0 = time.process_time()
    for k in range(records):
        step_record(k, 1, ws, fs, reading, 100.0 + k, after, outs)
    return (time.process_time() - t0) / records * 1e6


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--sends", type=int, default=5000)
    p.add_argument("--json", type=Path, default=None)
    args = p.parse_args(argv)
    off, on = send_cost(args.sends, False), send_cost(args.sends, True)
    w = writer_cost()
    w_off, w_on = watch_cost(args.sends * 4, False), watch_cost(args.sends * 4, True)
    per_record = step_record_cost()
    w_untracked = writer_cost(tracking=False)
    t_off, t_on = tracking_cost(args.sends * 2, False), tracking_cost(args.sends * 2, True)
    t_rec = tracking_record_cost()
    print(f"setpoint send (pymavlink encode + write), {args.sends} sends:")
    print(f"  {'':22s} {'median us':>10s} {'p99 us':>10s} {'max us':>10s}")
    for name, r in (("without the recorder", off), ("with the recorder", on)):
        print(f"  {name:22s} {r['median_us']:10.2f} {r['p99_us']:10.2f} {r['max_us']:10.1f}")
    print(f"writer thread, one minute of flight traffic: {w['records']:.0f} records, {w['cpu_s']:.2f} s CPU "
          f"({w['core_percent']:.1f} % of a core), {w['file_kb']:.0f} kB written")
    print(f"autopilot watch (position or link check: its rules, and the observer), {args.sends * 4} calls:")
    for name, r in (("without the recorder", w_off), ("with the recorder", w_on)):
        print(f"  {name:22s} {r['median_us']:10.2f} {r['p99_us']:10.2f} {r['max_us']:10.1f}")
    print(f"writer thread, an /autopilot/step record: {per_record:.1f} us CPU")
    print(f"tracking error (check_tracking: its rules, and the observer), {args.sends * 2} calls:")
    for name, r in (("without the recorder", t_off), ("with the recorder", t_on)):
        print(f"  {name:22s} {r['median_us']:10.2f} {r['p99_us']:10.2f} {r['max_us']:10.1f}")
    print(f"writer thread, a /tracking/step record: {t_rec['convert_us']:.1f} us CPU, {t_rec['json_bytes']:.0f} bytes "
          f"of JSON, {t_rec['zstd_bytes']:.0f} compressed; a minute's file {w_untracked['file_kb']:.0f} kB without "
          f"them, {w['file_kb']:.0f} kB with")
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps({"send_without": off, "send_with": on, "writer": w, "watch_without": w_off,
                                         "watch_with": w_on, "step_record_us": per_record,
                                         "writer_without_tracking": w_untracked, "tracking_without": t_off,
                                         "tracking_with": t_on, "tracking_record": t_rec}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
