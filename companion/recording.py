"""`python -m companion recording summary FILE.mcap`: what a recorded flight holds, in numbers.

Duration, messages per channel, the setpoint stream (count, rate, gaps), tracking error (as the
companion measured it, from its status), plans and replans with their latencies, events, and
what the recorder dropped. Read with the `mcap` reader, nothing of the writer's.
"""

from __future__ import annotations

import collections
import json
import struct
import sys
from collections.abc import Iterator
from typing import Any

import numpy as np

SETPOINT = "/mavlink/out/SET_POSITION_TARGET_LOCAL_NED"


def read_messages(path: str, topics: list[str] | None = None) -> Iterator[tuple[Any, Any, Any]]:
    """(schema, channel, message) of a file in log-time order; a file cut short (a crash, no
    summary) is read in file order up to its last complete chunk, with a warning."""
    from mcap.exceptions import EndOfFile, McapError
    from mcap.reader import make_reader
    from mcap.records import Channel, Message, Schema
    from mcap.stream_reader import StreamReader

    with open(path, "rb") as fh:
        try:
            summary = make_reader(fh).get_summary()
        except (McapError, ValueError):
            summary = None
        if summary is not None:
            fh.seek(0)
            yield from make_reader(fh).iter_messages(topics=topics)
            return
        print(f"{path}: no summary (the recording was cut short?): reading its complete chunks in order",
              file=sys.stderr)
        fh.seek(0)
        schemas: dict[int, Any] = {}
        channels: dict[int, Any] = {}
        try:
            for record in StreamReader(fh).records:
                if isinstance(record, Schema):
                    schemas[record.id] = record
                elif isinstance(record, Channel):
                    channels[record.id] = record
                elif isinstance(record, Message):
                    channel = channels.get(record.channel_id)
                    if channel is not None and (topics is None or channel.topic in topics):
                        yield schemas.get(channel.schema_id), channel, record
        except (EndOfFile, McapError, struct.error, ValueError):  # the cut
            return


def summarize(path: str) -> dict[str, Any]:
    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    counts: collections.Counter[str] = collections.Counter()
    sizes: collections.Counter[str] = collections.Counter()
    sp_t: list[float] = []
    tracking: list[float] = []
    plans: list[dict[str, Any]] = []
    events: list[dict[str, Any]] = []
    stats: dict[str, Any] = {}
    first = last = None
    try:
        with open(path, "rb") as fh:
            meta = {m.name: dict(m.metadata) for m in make_reader(fh).iter_metadata()}
    except (McapError, ValueError):
        meta = {}
    for _schema, channel, message in read_messages(path):
        topic = channel.topic
        counts[topic] += 1
        sizes[topic] += len(message.data)
        first = message.log_time if first is None else min(first, message.log_time)
        last = message.log_time if last is None else max(last, message.log_time)
        if topic == SETPOINT:
            sp_t.append(json.loads(message.data)["t"])
        elif topic == "/out/status":
            err = json.loads(message.data).get("tracking_error")
            if isinstance(err, int | float):
                tracking.append(float(err))
        elif topic == "/planner/plan":
            rec = json.loads(message.data)
            plans.append({k: rec.get(k) for k in ("seq", "function", "ok", "status", "latency_ms", "message")})
        elif topic == "/out/events":
            e = json.loads(message.data)
            events.append({k: e.get(k) for k in ("time", "type", "message")})
        elif topic == "/recorder/stats":
            stats = json.loads(message.data)
    out: dict[str, Any] = {
        "file": path,
        "duration_s": None if first is None or last is None else round((last - first) / 1e9, 3),
        "channels": {t: {"messages": counts[t], "bytes": sizes[t]} for t in sorted(counts)},
        "setpoints": setpoint_stats(np.asarray(sorted(sp_t))),
        "tracking_error_m": None if not tracking else {
            "mean": round(float(np.mean(tracking)), 4), "max": round(float(np.max(tracking)), 4)},
        "plans": plans,
        "plans_by_function": dict(collections.Counter(p["function"] for p in plans)),
        "events": events,
        "events_by_type": dict(collections.Counter(str(e["type"]) for e in events)),
        "recorder": stats,
        "metadata": {k: {kk: vv for kk, vv in v.items() if kk != "config"} for k, v in meta.items()},
    }
    return out


def setpoint_stats(t: np.ndarray, pause: float = 0.5) -> dict[str, Any]:
    """Count, rate over the streaming stretches (gaps over `pause` s split them) and gaps."""
    if len(t) < 2:
        return {"count": len(t)}
    d = np.diff(t)
    streaming = d[d <= pause]
    return {
        "count": len(t),
        "span_s": round(float(t[-1] - t[0]), 3),
        "rate_hz": round(float(len(streaming) / np.sum(streaming)), 3) if len(streaming) else None,
        "period_p99_ms": round(float(np.percentile(streaming, 99) * 1000), 3) if len(streaming) else None,
        "gap_max_ms": round(float(np.max(streaming) * 1000), 3) if len(streaming) else None,
        "pauses": int(np.sum(d > pause)),
    }


def render(s: dict[str, Any]) -> str:
    lines = [f"{s['file']}: {s['duration_s']} s"]
    lines.append("channels:")
    for topic, c in s["channels"].items():
        lines.append(f"  {topic:50s} {c['messages']:8d} msgs {c['bytes'] / 1024:10.1f} kB")
    sp = s["setpoints"]
    lines.append(f"setpoints: {sp.get('count')} sent, {sp.get('rate_hz')} Hz while streaming, period p99 "
                 f"{sp.get('period_p99_ms')} ms, longest gap {sp.get('gap_max_ms')} ms, {sp.get('pauses', 0)} pause(s) > 0.5 s")
    te = s["tracking_error_m"]
    lines.append("tracking error: " + ("none reported" if te is None else f"mean {te['mean']} m, max {te['max']} m"))
    lines.append(f"plans: {len(s['plans'])} ({', '.join(f'{k} x{v}' for k, v in s['plans_by_function'].items())})")
    for p in s["plans"]:
        lines.append(f"  #{p['seq']} {p['function']}: {p['status']} in {p['latency_ms']} ms"
                     + (f" ({p['message']})" if p.get("message") and not p.get("ok") else ""))
    lines.append(f"events: {', '.join(f'{k} x{v}' for k, v in s['events_by_type'].items()) or 'none'}")
    for e in s["events"]:
        lines.append(f"  {e['type']}: {str(e['message'])[:160]}")
    rec = s["recorder"]
    lines.append(f"recorder: {rec.get('written')} records written, {rec.get('dropped_total', 0)} dropped "
                 f"{rec.get('dropped') or ''}")
    return "\n".join(lines)


def extract(path: str, out: str, channels: list[str]) -> int:
    """Copy the named channels (and the file's metadata) to a new file: e.g. only the planner
    calls of a field flight, a small regression test for `replay`. Returns messages copied."""
    from mcap.reader import make_reader
    from mcap.writer import CompressionType, Writer

    n = 0
    with open(path, "rb") as fh, open(out, "wb") as dst:
        reader = make_reader(fh)
        writer = Writer(dst, compression=CompressionType.ZSTD)
        writer.start(profile="", library="bezier-companion recording extract")
        for m in reader.iter_metadata():
            writer.add_metadata(m.name, dict(m.metadata))
        schemas: dict[int, int] = {}
        chans: dict[int, int] = {}
        for schema, channel, message in reader.iter_messages(topics=channels):
            if channel.id not in chans:
                if schema is not None and schema.id not in schemas:
                    schemas[schema.id] = writer.register_schema(schema.name, schema.encoding, schema.data)
                chans[channel.id] = writer.register_channel(channel.topic, channel.message_encoding,
                                                            schemas[schema.id] if schema is not None else 0)
            writer.add_message(chans[channel.id], log_time=message.log_time, data=message.data,
                               publish_time=message.publish_time)
            n += 1
        writer.finish()  # type: ignore[no-untyped-call]  # mcap's Writer.finish has no annotations
    return n


def main(argv: list[str]) -> int:
    import argparse

    p = argparse.ArgumentParser(prog="python -m companion recording", description=__doc__.splitlines()[0])
    sub = p.add_subparsers(dest="what", required=True)
    s = sub.add_parser("summary", help="what a recorded flight holds")
    s.add_argument("file")
    s.add_argument("--json", action="store_true", help="print the summary as JSON")
    x = sub.add_parser("extract", help="copy some channels to a new file (e.g. --channel /planner/plan)")
    x.add_argument("file")
    x.add_argument("out")
    x.add_argument("--channel", action="append", required=True, metavar="TOPIC")
    args = p.parse_args(argv)
    if args.what == "extract":
        try:
            n = extract(args.file, args.out, args.channel)
        except (OSError, ValueError) as exc:
            print(f"recording: {exc}", file=sys.stderr)
            return 2
        print(f"{n} messages copied to {args.out}")
        return 0 if n else 1
    try:
        summary = summarize(args.file)
    except (OSError, ValueError) as exc:
        print(f"recording: {args.file}: {exc}", file=sys.stderr)
        return 2
    print(json.dumps(summary, indent=2) if args.json else render(summary))
    return 0
