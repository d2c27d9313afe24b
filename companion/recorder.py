"""The flight recorder: everything in and out of the service, as MCAP, and the same channels live.

`Recorder` is the service's `Tap` (companion/tap.py). A call only stamps and enqueues (O(1),
`put_nowait` on a bounded queue; never a wait, never a conversion), so neither the loop nor
the setpoint thread ever waits on a disk or a viewer. A writer thread of its own converts
each record (JSON, MAVLink to dict, planner arguments pickled, Foxglove 3D messages) and hands
it to the sinks: `McapSink` (one MCAP file per run, rotated at `[recording] max_bytes`, the
oldest removed past `keep_bytes`) and `companion.live.LiveSink` (the Foxglove WebSocket
server). A record that finds its queue full is dropped and counted: in status
(`recording.dropped`), in the `/recorder/stats` channel every second and in the file's
`recorder` metadata record. Setpoints (every MAVLink message sent) have a queue of their own,
so a burst of other traffic never drops one; so have the decisions replay checks as unbroken
chains: the supervisor's transitions (every `Supervisor.handle` call), the autopilot watch's
steps (every call of companion.autopilot_rules.watch_step), the tracking error's (every call
of companion.tracking_rules.tracking_step that changed or said something), the split-and-swap
loop's (every call of companion.split_rules.split_step), the plan budget's (every call of
companion.plan_budget.budget_step), the pop-ups' (every call of companion.race_rules.race_step),
the fleet's commit protocol's (every call of companion.commit.step), the operator commands'
sequences' (every call of companion.command_rules.command_step), the stall watch's (every call
of companion.stall_rules.stall_step that changed or found something), the hand-over's hold
(every call of companion.hold_rules.hold_step) and the navigator's plan choice (every call of
companion.choice_rules.choice_step).

Channels, schemas and frames: companion/channels.py (the 3D messages: companion/viz3d.py) and
docs/recording.md.
"""

from __future__ import annotations

import contextlib
import datetime
import itertools
import json
import logging
import os
import queue
import threading
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any, Protocol

from companion import channels as ch
from companion.config import Config, config_to_toml
from companion.record_bodies import (
    decoded_record,
    plan_record,
    step_record,
    swap_record,
    tracking_record,
    transition_record,
)
from companion.record_format import environment
from companion.tap import Tap
from companion.viz3d import Viz

log = logging.getLogger("companion")

FORMAT_VERSION = "1"
STATS_PERIOD = 1.0  # s between /recorder/stats records
CHUNK_BYTES = 128 * 1024  # uncompressed MCAP chunk


class Sink(Protocol):
    def write(self, topic: str, data: bytes, log_time: int) -> None: ...

    def close(self, stats: dict[str, Any]) -> None: ...


# -- MCAP files ---------------------------------------------------------------------------------


class McapSink:
    """One MCAP file per run in `directory`, a new one past `max_bytes` (`-001`, `-002`, ...);
    the oldest `.mcap` files there are removed while they hold more than `keep_bytes` in all."""

    def __init__(self, directory: Path, stem: str, max_bytes: int, keep_bytes: int,
                 metadata: dict[str, str]) -> None:
        self.directory = directory
        self.stem = stem
        self.max_bytes = max_bytes
        self.keep_bytes = keep_bytes
        self.metadata = metadata
        self.part = 0
        self.files: list[Path] = []
        self._writer: Any = None
        self._fh: Any = None
        self._schemas: dict[str, int] = {}
        self._channels: dict[str, int] = {}
        directory.mkdir(parents=True, exist_ok=True)
        self._open()

    @property
    def path(self) -> Path:
        return self.files[-1]

    def _open(self) -> None:
        from mcap.writer import CompressionType, Writer

        name = self.stem + (f"-{self.part:03d}" if self.part else "") + ".mcap"
        path = self.directory / name
        self._fh = open(path, "wb")  # noqa: SIM115 - closed in _finish
        # zstd chunks (JSON telemetry compresses ~10x) of 128 kB: a crash loses the chunk being
        # filled, ~5 s of flight, never the file's earlier chunks
        self._writer = Writer(self._fh, compression=CompressionType.ZSTD,
                              chunk_size=max(4096, min(CHUNK_BYTES, self.max_bytes // 8)))
        self._writer.start(profile="", library=f"bezier-companion recorder {FORMAT_VERSION}")
        self._writer.add_metadata("companion", {**self.metadata, "part": str(self.part)})
        self._schemas.clear()
        self._channels.clear()
        self.files.append(path)
        self._prune()

    def _channel(self, topic: str) -> int:
        cid = self._channels.get(topic)
        if cid is None:
            spec = ch.spec(topic)
            sid = self._schemas.get(spec.schema_name)
            if sid is None:
                sid = self._writer.register_schema(spec.schema_name, spec.schema_encoding, spec.schema_data)
                self._schemas[spec.schema_name] = sid
            cid = self._writer.register_channel(topic, spec.message_encoding, sid)
            self._channels[topic] = cid
        return cid

    def write(self, topic: str, data: bytes, log_time: int) -> None:
        self._writer.add_message(self._channel(topic), log_time=log_time, data=data, publish_time=log_time)
        if self._fh.tell() >= self.max_bytes:
            self._finish({"rotated": "true"})
            self.part += 1
            self._open()

    def _finish(self, meta: dict[str, str]) -> None:
        with contextlib.suppress(Exception):
            self._writer.add_metadata("recorder", meta)
        self._writer.finish()
        self._fh.close()

    def close(self, stats: dict[str, Any]) -> None:
        self._finish({k: json.dumps(v) for k, v in stats.items()})

    def _prune(self) -> None:
        """Remove the oldest recordings (never the one being written) past keep_bytes."""
        files = sorted((p for p in self.directory.glob("*.mcap") if p != self.path),
                       key=lambda p: p.stat().st_mtime)
        total = sum(p.stat().st_size for p in files)
        for p in files:
            if total <= self.keep_bytes:
                break
            with contextlib.suppress(OSError):
                size = p.stat().st_size
                p.unlink()
                total -= size
                log.info("recording: removed %s ([recording] keep_bytes = %d)", p.name, self.keep_bytes)


# -- the recorder -------------------------------------------------------------------------------


class Recorder(Tap):
    """The service's tap when `[recording] path` or `[live] foxglove` is set."""

    def __init__(self, cfg: Config, sinks: list[Sink] | None = None,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.cfg = cfg
        self.clock = clock
        # log times are wall-clock ns (what viewers show); records keep the monotonic time
        # they were taken at, and the offset between the two is in the file's metadata
        self.offset = time.time() - clock()
        size = cfg.recording.queue
        self._sent: queue.Queue[tuple[Any, ...]] = queue.Queue(size)  # MAVLink sent: setpoints
        self._rest: queue.Queue[tuple[Any, ...]] = queue.Queue(size)
        # the supervisor's transitions: a few to tens a second, and replay needs every one of
        # them (a gap breaks the chain it checks), so an inbound flood must not crowd them out
        self._decisions: queue.Queue[tuple[Any, ...]] = queue.Queue(size)
        self._drop_lock = threading.Lock()
        self.dropped: dict[str, int] = {}
        self.written = 0
        self.sinks: list[Sink] = list(sinks or [])
        self.mcap: McapSink | None = None
        self._viz = Viz()
        self._viz.offset = self.offset
        self._plan_seq = itertools.count(1)
        self._transition_seq = itertools.count(1)
        self._decoded_seq = itertools.count(1)
        self._step_seq = itertools.count(1)
        self._swap_seq = itertools.count(1)
        self._tracking_seq = itertools.count(1)
        self._split_seq = itertools.count(1)
        self._budget_seq = itertools.count(1)
        self._race_seq = itertools.count(1)
        self._commit_seq = itertools.count(1)
        self._clock_seq = itertools.count(1)
        self._swaps = 0  # swaps numbered so far (on the loop, as the split's steps are recorded)
        self._command_seq = itertools.count(1)
        self._stall_seq = itertools.count(1)
        self._hold_seq = itertools.count(1)
        self._choice_seq = itertools.count(1)
        # the writer's: the last /tracking/step seq written and the file part it went to; a
        # record after a gap, or the first of a part, carries its window of errors in full
        self._tracking_written: tuple[int, int] = (0, 0)
        self._transitions = 0  # transitions numbered so far (on the loop, as both taps are called)
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None
        self._last_stats = 0.0
        self.error: str | None = None  # why a sink was given up, for status

    # -- opening --------------------------------------------------------------------------

    def open(self) -> None:
        """Open the file (if `[recording] path`) and the live server (if `[live] foxglove`);
        start the writer thread."""
        rc = self.cfg.recording
        # every import the writer thread needs, now: an import mid-flight holds the import lock
        # and the GIL in long stretches
        import foxglove.messages  # noqa: F401
        import mcap.writer  # noqa: F401
        import scipy.spatial  # noqa: F401

        from companion import obstacles, record_format  # noqa: F401

        # Neither a recording that cannot be written nor a live port in use stops the service: it
        # says so (log, status `recording.error`) and flies without.
        if rc.path:
            stamp = datetime.datetime.now(datetime.UTC).strftime("%Y%m%dT%H%M%SZ")
            stem = f"{self.cfg.vehicle.id}-{stamp}-{os.getpid()}"
            try:
                self.mcap = McapSink(Path(rc.path), stem, rc.max_bytes, rc.keep_bytes, self.metadata())
                self.sinks.append(self.mcap)
                log.info("recording to %s", self.mcap.path)
            except Exception as exc:
                self._failed(f"[recording] path {rc.path!r}: {exc}")
        if self.cfg.live.foxglove:
            from companion.live import LiveSink

            try:
                self.sinks.append(LiveSink.start(self.cfg.live.foxglove, self.cfg.vehicle.id))
            except Exception as exc:
                self._failed(f"[live] foxglove {self.cfg.live.foxglove!r}: {exc}")
        self._thread = threading.Thread(target=self._main, name="recorder", daemon=True)
        self._thread.start()

    def _failed(self, why: str) -> None:
        self.error = why
        log.error("flight recorder: %s; going on without it", why)

    def metadata(self) -> dict[str, str]:
        return {
            "format": FORMAT_VERSION,
            "vehicle": self.cfg.vehicle.id,
            "monotonic_to_unix": repr(self.offset),
            "config": config_to_toml(self.cfg),
            "started": datetime.datetime.now(datetime.UTC).isoformat(),
            "frames": ch.FRAMES_NOTE,
            "environment": json.dumps(environment()),
        }

    # -- the tap: O(1), never waits --------------------------------------------------------

    def _put(self, q: queue.Queue[tuple[Any, ...]], item: tuple[Any, ...]) -> None:
        try:
            q.put_nowait(item)
        except queue.Full:
            with self._drop_lock:
                self.dropped[item[0]] = self.dropped.get(item[0], 0) + 1

    def inbound(self, key: str, payload: Any, t: float) -> None:
        self._put(self._rest, ("inbound", key, payload, t))

    def outbound(self, key: str, payload: bytes, t: float) -> None:
        self._put(self._rest, ("outbound", key, payload, t))

    def decoded(self, key: str, payload: Any, context: dict[str, Any], result: Any, t: float) -> None:
        self._put(self._rest, ("decoded", next(self._decoded_seq), key, payload, context, result, t))

    def mavlink_sent(self, msg: Any, t: float | None = None) -> None:
        # called by pymavlink's send callback, in whichever thread sent (the setpoint thread)
        self._put(self._sent, ("mavlink_sent", msg, self.clock() if t is None else t))

    def mavlink_received(self, msg: Any, t: float) -> None:
        self._put(self._rest, ("mavlink_received", msg, t))

    def plan(self, fn: Any, args: tuple[Any, ...], result: Any, submitted: float, done: float,
             where: str) -> None:
        if getattr(fn, "__name__", "").startswith("warm_up"):
            return
        self._put(self._rest, ("plan", fn, args, result, submitted, done, where))

    def transition(self, before: Any, event: Any, after: Any, actions: tuple[Any, ...]) -> None:
        # the number is taken here, on the caller's thread, before the put: a record dropped
        # for a full queue leaves a gap in the file's numbers, which replay reports
        seq = self._transitions = next(self._transition_seq)
        self._put(self._decisions, ("transition", seq, before, event, after, actions, self.clock()))

    def autopilot_step(self, before: Any, flight: Any, reading: Any, now: float, after: Any,
                       outputs: tuple[Any, ...]) -> None:
        # numbered as transitions are; with the number the step's first event gets from
        # `transition` (the watch hands its events to the supervisor right after), so that
        # replay can find the transitions each step caused
        self._put(self._decisions, ("autopilot_step", next(self._step_seq), self._transitions + 1, before, flight,
                                    reading, now, after, outputs))

    def swap(self, what: str, now: float, lead: float, rate_hz: float, t_split: float, old: Any, new: Any,
             refusal: str) -> None:
        seq = self._swaps = next(self._swap_seq)
        self._put(self._decisions, ("swap", seq, what, now, lead, rate_hz, t_split, old, new, refusal, self.clock()))

    def tracking_step(self, before: Any, reading: Any, after: Any, outputs: tuple[Any, ...], t: float) -> None:
        # numbered as autopilot steps are, with the next transition's number: the brake it asks
        # for is a transition after it, which replay finds
        self._put(self._decisions, ("tracking_step", next(self._tracking_seq), self._transitions + 1, before, reading,
                                    after, outputs, t))

    def split_step(self, call: int, step: int, what: str, rules: Any, before: Any, observation: Any, after: Any,
                   action: Any) -> None:
        # with the number of the last swap decided: a step that observed a swap names its record
        self._put(self._decisions, ("split_step", next(self._split_seq), self._swaps, call, step, what, rules, before,
                                    observation, after, action, self.clock()))

    def commit_step(self, before: Any, event: Any, after: Any, actions: tuple[Any, ...]) -> None:
        self._put(self._decisions, ("commit_step", next(self._commit_seq), before, event, after, actions,
                                    self.clock()))

    def clock_sample(self, vehicle: str, sent: float, arrived: float, off: str | None) -> None:
        self._put(self._decisions, ("clock_sample", next(self._clock_seq), vehicle, sent, arrived, off, self.clock()))

    def budget_step(self, before: Any, ask: Any, after: Any, answer: Any) -> None:
        self._put(self._decisions, ("budget_step", next(self._budget_seq), before, ask, after, answer, self.clock()))

    def race_step(self, race: int, step: int, rules: Any, before: Any, observation: Any, after: Any,
                  action: Any) -> None:
        # with the next transition's number, as tracking steps: a brake's Braking transition comes at or after it
        self._put(self._decisions, ("race_step", next(self._race_seq), self._transitions + 1, race, step, rules,
                                    before, observation, after, action, self.clock()))

    def command_step(self, call: int, step: int, rules: Any, before: Any, observation: Any, after: Any,
                     action: Any) -> None:
        # with the next transition's number, as autopilot steps are: a step whose action is a
        # transition makes that one (the sequence hands it to the supervisor right after)
        self._put(self._decisions, ("command_step", next(self._command_seq), self._transitions + 1, call, step, rules,
                                    before, observation, after, action, self.clock()))

    def stall_step(self, rules: Any, before: Any, observation: Any, after: Any, action: Any) -> None:
        # with the next transition's number: a hold or a release after a stall makes its
        # transitions at or after it
        self._put(self._decisions, ("stall_step", next(self._stall_seq), self._transitions + 1, rules, before,
                                    observation, after, action, self.clock()))

    def hold_step(self, call: int, step: int, rules: Any, before: Any, observation: Any, after: Any,
                  action: Any) -> None:
        self._put(self._decisions, ("hold_step", next(self._hold_seq), call, step, rules, before, observation, after,
                                    action, self.clock()))

    def choice_step(self, call: int, step: int, rules: Any, before: Any, observation: Any, after: Any,
                    action: Any) -> None:
        self._put(self._decisions, ("choice_step", next(self._choice_seq), call, step, rules, before, observation,
                                    after, action, self.clock()))

    def flown(self, trajectory: Any, t_base: float | None, t: float) -> None:
        self._put(self._rest, ("flown", trajectory, t_base, t))

    def status_fields(self) -> dict[str, Any]:
        with self._drop_lock:  # the dict grows from other threads
            dropped = sum(self.dropped.values())
        return {"recording": {
            "file": str(self.mcap.path) if self.mcap is not None else None,
            "written": self.written,
            "dropped": dropped,
            "error": self.error,
        }}

    def stats(self) -> dict[str, Any]:
        with self._drop_lock:
            dropped = dict(self.dropped)
        return {"written": self.written, "dropped": dropped, "dropped_total": sum(dropped.values()),
                "queued": self._sent.qsize() + self._decisions.qsize() + self._rest.qsize()}

    # -- the writer thread -----------------------------------------------------------------

    def close(self) -> None:
        """Write out what is queued (bounded: systemd's stop timeout follows the hand-over) and
        close the sinks; a writer still busy then leaves its file without a summary."""
        self._stop.set()
        if self._thread is not None:
            self._thread.join(3.0)
            if self._thread.is_alive():
                log.error("flight recorder: still writing after 3 s at stop; the file is left without "
                          "its summary (docs/recording.md: reading a file cut short)")
                return
        stats = self.stats()
        for sink in self.sinks:
            try:
                sink.close(stats)
            except Exception:
                log.exception("recording: closing %r failed", sink)

    def _main(self) -> None:
        from companion.setpoints import name_thread

        name_thread("recorder")
        while True:
            stopping = self._stop.is_set()
            n = self._drain(self._sent) + self._drain(self._decisions) + self._drain(self._rest)
            now = self.clock()
            if now - self._last_stats >= STATS_PERIOD:
                self._last_stats = now
                self._emit("/recorder/stats", ch.dumps({"t": now, **self.stats()}), now)
            if stopping and n == 0:
                return
            if n == 0:
                self._stop.wait(0.02)

    def _drain(self, q: queue.Queue[tuple[Any, ...]], most: int = 2000) -> int:
        n = 0
        while n < most:
            try:
                item = q.get_nowait()
            except queue.Empty:
                break
            n += 1
            try:
                self._convert(item)
            except Exception:  # a record we cannot convert must not end the recording
                log.exception("recording: could not record a %s", item[0])
        return n

    def _emit(self, topic: str, data: bytes, t: float) -> None:
        log_time = int((t + self.offset) * 1e9)
        for sink in self.sinks:
            try:
                sink.write(topic, data, log_time)
            except Exception as exc:  # a full disk, a server gone: give that sink up, once
                self.sinks = [s for s in self.sinks if s is not sink]
                self._failed(f"writing {topic} to {type(sink).__name__} failed ({exc!r})")
        self.written += 1

    def _convert(self, item: tuple[Any, ...]) -> None:
        kind = item[0]
        if kind == "inbound":
            _, key, payload, t = item
            self._emit(f"/in/{key}", ch.inbound_record(key, payload, t), t)
        elif kind == "outbound":
            _, key, payload, t = item
            self._emit(f"/out/{key}", bytes(payload), t)
        elif kind in ("mavlink_sent", "mavlink_received"):
            _, msg, t = item
            name = msg.get_type()
            way = "out" if kind == "mavlink_sent" else "in"
            self._emit(f"/mavlink/{way}/{name}", ch.mavlink_record(msg, t), t)
            if way == "in":
                for topic, data in self._viz.on_mavlink(msg, t):
                    self._emit(topic, data, t)
        elif kind == "plan":
            _, fn, args, result, submitted, done, where = item
            seq = next(self._plan_seq)
            self._emit("/planner/plan", plan_record(seq, fn, args, result, submitted, done, where, self.cfg), done)
            for topic, data in self._viz.on_plan(args, result, done):
                self._emit(topic, data, done)
        elif kind == "decoded":
            _, seq, key, payload, context, result, t = item
            self._emit("/inbound/decoded", decoded_record(seq, key, payload, context, result, t), t)
        elif kind == "transition":
            _, seq, before, event, after, actions, t = item
            self._emit("/supervisor/transition", transition_record(seq, t, before, event, after, actions), t)
        elif kind == "autopilot_step":
            # logged at the time the rules were given (the service's monotonic clock), which
            # the record holds once, as `t`
            _, seq, first, before, flight, reading, now, after, outputs = item
            self._emit("/autopilot/step", step_record(seq, first, before, flight, reading, now, after, outputs), now)
        elif kind == "swap":
            _, seq, what, now, lead, rate_hz, t_split, old, new, refusal, t = item
            self._emit("/control/swap", swap_record(seq, t, what, now, lead, rate_hz, t_split, old, new, refusal), t)
        elif kind == "tracking_step":
            _, seq, first, before, reading, after, outputs, t = item
            part = self.mcap.part if self.mcap is not None else 0
            keyframe = self._tracking_written != (seq - 1, part)
            self._tracking_written = (seq, part)
            self._emit("/tracking/step", tracking_record(seq, first, t, before, reading, after, outputs, keyframe), t)
        elif kind == "split_step":
            _, seq, swap, call, step, what, rules, before, observation, after, action, t = item
            body = ch.split_fields(call, step, what, rules, before, observation, after, action)
            self._emit("/navigator/split", ch.dumps({"seq": seq, "t": t, "swap": swap, **body}), t)
        elif kind == "commit_step":
            _, seq, before, event, after, actions, t = item
            self._emit("/fleet/commit", ch.dumps({"seq": seq, "t": t, **ch.commit_fields(before, event, after, actions)}), t)
        elif kind == "clock_sample":
            _, seq, vehicle, sent, arrived, off, t = item
            self._emit("/fleet/clock", ch.dumps({"seq": seq, "t": t, "vehicle": vehicle, "sent": sent,
                                                 "arrived": arrived, "off": off}), t)
        elif kind == "budget_step":
            _, seq, before, ask, after, answer, t = item
            self._emit("/navigator/budget", ch.dumps({"seq": seq, "t": t, **ch.budget_fields(before, ask, after, answer)}), t)
        elif kind == "race_step":
            _, seq, first, race, step, rules, before, observation, after, action, t = item
            body = ch.split_fields(race, step, rules.what, rules, before, observation, after, action)  # the same fields
            self._emit("/brakes/race", ch.dumps({"seq": seq, "t": t, "transition": first, **body}), t)
        elif kind == "command_step":
            _, seq, transition, call, step, rules, before, observation, after, action, t = item
            body = ch.command_fields(call, step, rules, before, observation, after, action)
            self._emit("/commands/step", ch.dumps({"seq": seq, "t": t, "transition": transition, **body}), t)
        elif kind == "stall_step":
            _, seq, transition, rules, before, observation, after, action, t = item
            self._emit("/stalls/step", ch.dumps({"seq": seq, "t": t, "transition": transition,
                                                 **ch.rule_fields(rules, before, observation, after, action)}), t)
        elif kind == "hold_step":
            _, seq, call, step, rules, before, observation, after, action, t = item
            body = ch.command_fields(call, step, rules, before, observation, after, action)  # the same fields
            self._emit("/handover/hold", ch.dumps({"seq": seq, "t": t, **body}), t)
        elif kind == "choice_step":
            _, seq, call, step, rules, before, observation, after, action, t = item
            body = ch.choice_fields(call, step, rules, before, observation, after, action)
            self._emit("/navigator/choice", ch.dumps({"seq": seq, "t": t, **body}), t)
        elif kind == "flown":
            _, traj, t_base, t = item
            for topic, data in self._viz.on_flown(traj, t_base, t):
                self._emit(topic, data, t)


def tap_for(cfg: Config) -> Tap:
    """The service's tap: a Recorder when recording or the live view is on, else the no-op."""
    if cfg.recording.path or cfg.live.foxglove:
        return Recorder(cfg)
    return Tap()
