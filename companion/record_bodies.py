"""The bodies of the records the recorder writes for the decisions replay runs again and for
the planner's calls: readable fields (companion.channels) and, where a record needs them, the
values pickled (base64) in 64 kB frames, so that no single C call holds the interpreter lock
long while the setpoint thread needs it. Called on the recorder's writer thread only.
"""

from __future__ import annotations

import base64
import pickle
from typing import Any

from companion import channels as ch
from companion.config import Config


def plan_record(seq: int, fn: Any, args: tuple[Any, ...], result: Any, submitted: float, done: float,
                where: str, cfg: Config) -> bytes:
    """One planner call: readable fields, and the call and its result pickled (base64) so that
    `python -m companion replay` can run it again and compare bit for bit. Built so that no
    single C call holds the interpreter lock for long (the setpoint thread needs it every tick):
    pickles are written in 64 kB frames through Python, the base64 text is spliced in, not
    passed through the JSON encoder."""
    from companion import record_format as fmt

    name = fmt.function_name(fn)
    compiled = fmt.compiled_used(result, cfg.planner.compiled if where == "process" else False)
    body: dict[str, Any] = {
        "seq": seq,
        "function": name,
        "where": where,
        "compiled": compiled,
        "submitted": submitted,
        "done": done,
        "latency_ms": round((done - submitted) * 1000, 3),
        **fmt.summary_of(result),
        "fingerprint": fmt.fingerprint(result),
    }
    call = _pickled((fn, args))
    res = None if isinstance(result, BaseException) else _pickled(result)
    return b"".join([ch.dumps(body)[:-1],
                     b',"call":', b"null" if call is None else b'"' + call + b'"',
                     b',"result":', b"null" if res is None else b'"' + res + b'"', b"}"])


def transition_record(seq: int, t: float, before: Any, event: Any, after: Any, actions: tuple[Any, ...]) -> bytes:
    """One `Supervisor.handle` call: readable fields (companion.channels.transition_fields) and
    the four values pickled together (base64), which `python -m companion replay` runs through
    `transition` again. One pickle, not four: the classes are named once (measured 27-38 % smaller)."""
    body = ch.transition_fields(before, event, after, actions)
    blob = _pickled((before, event, after, actions))
    return b"".join([ch.dumps({"seq": seq, "t": t, **body})[:-1],
                     b',"pickle":', b"null" if blob is None else b'"' + blob + b'"', b"}"])


def step_record(seq: int, transition: int, before: Any, flight: Any, reading: Any, now: float,
                after: Any, outputs: tuple[Any, ...]) -> bytes:
    """One call of the autopilot watch's rules: readable fields (companion.channels.step_fields)
    and the six values pickled together (base64), which `python -m companion replay` runs through
    `watch_step` again."""
    body = ch.step_fields(before, flight, reading, now, after, outputs)
    blob = _pickled((before, flight, reading, now, after, outputs))
    return b"".join([ch.dumps({"seq": seq, "transition": transition, **body})[:-1],
                     b',"pickle":', b"null" if blob is None else b'"' + blob + b'"', b"}"])


def tracking_record(seq: int, transition: int, t: float, before: Any, reading: Any, after: Any,
                    outputs: tuple[Any, ...], keyframe: bool) -> bytes:
    """One call of the tracking error's rules (companion.channels.tracking_fields), which
    `python -m companion replay` runs through `tracking_step` again. JSON only, no pickle: every
    value is a number, a flag or a string, which JSON holds exactly (a float by its shortest
    repr), at half the bytes. The states are recorded as `StateSeen` (the window of errors by its
    length and digest: the errors are the readings of the records before); a `keyframe` (the
    first record of a file, or after a gap) holds the window before in full, for replay to start from."""
    from companion.tracking_rules import StateSeen

    window = before.errors if keyframe and before.errors else None
    body = ch.tracking_fields(StateSeen.of(before), reading, StateSeen.of(after), outputs, window)
    return ch.dumps({"seq": seq, "transition": transition, "t": t, **body})


def decoded_record(seq: int, key: str, payload: Any, context: dict[str, Any], result: Any, t: float) -> bytes:
    """One inbound message read: what it became (readable, and a fingerprint) and the call's
    inputs pickled (base64), which `python -m companion replay` reads again and compares. The
    result is not pickled: a typed message is its fingerprint and the refusal its words."""
    from companion import record_format as fmt

    body: dict[str, Any] = {"seq": seq, "key": key, "t": t, **fmt.decoded_summary(result),
                            "fingerprint": fmt.decoded_fingerprint(result)}
    raw = bytes(payload) if isinstance(payload, bytes | bytearray | memoryview) else len(payload)
    call = _pickled((key, raw, context.get("home"), bool(context.get("home_pending")), context.get("fleet"),
                     context.get("autopilot")))
    return b"".join([ch.dumps(body)[:-1], b',"call":', b"null" if call is None else b'"' + call + b'"', b"}"])


class _Frames:
    """A file for pickle.Pickler: a Python-level write per 64 kB frame is where other threads
    get the interpreter lock back while a large result is pickled."""

    def __init__(self) -> None:
        self.parts: list[bytes] = []

    def write(self, data: Any) -> int:  # bytes, or a PickleBuffer (a large array's data)
        part = bytes(data)
        self.parts.append(part)
        return len(part)


def _pickled(obj: Any) -> bytes | None:
    try:
        out = _Frames()
        pickle.Pickler(out, protocol=5).dump(obj)
        return base64.b64encode(b"".join(out.parts))
    except Exception:  # not picklable: the plan is recorded, but replay cannot run it
        return None


def swap_record(seq: int, t: float, what: str, now: float, lead: float, rate_hz: float, t_split: float,
                old: Any, new: Any, refusal: str) -> bytes:
    """One decision of the swap's rule: readable fields (companion.channels.swap_fields) and the
    two trajectories pickled together (base64), which `python -m companion replay` decides again
    with companion.control.swap_refusal."""
    from companion.control import swap_span

    # what the rule reads: the segments from now to the split, the curves alone (a 1000-waypoint
    # mission's two trajectories would be ~0.6 MB a swap; the corridors are in the plan records)
    old, new = swap_span(old, now, t_split), swap_span(new, now, t_split)
    body = ch.swap_fields(what, now, lead, rate_hz, t_split, old, new, refusal)
    blob = _pickled((old, new))
    return b"".join([ch.dumps({"seq": seq, "t": t, **body})[:-1],
                     b',"pickle":', b"null" if blob is None else b'"' + blob + b'"', b"}"])
