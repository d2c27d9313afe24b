"""`python -m companion replay FILE.mcap`: run every recorded plan again and compare bit for bit.

What it covers: the planner boundary. Each `/planner/plan` record holds the planner call the
service made (the function and its arguments: the mission, the jet to start from, the known
obstacles, the configuration, the route and trajectory being replanned) and its result. Replay
runs the same function on the same arguments, in this process, with the same planner path
(the numpy path unless the record says the compiled one ran), and compares the result with the
recorded one: every array bit for bit, every number by its exact binary value, every string,
leaving out only the `stats` dictionaries (timings). What it does not cover: the service's
decisions around the planner (which message led to which call, when a plan was swapped in) are
not re-run; they are in the file (inbound messages, events, what was flown) to be read.

A recording comes from a companion you trust: the calls are pickled. They are read with an
allow-list (planner_core and companion data classes and planner functions, numpy arrays,
plain containers), so a file cannot name any other function to call; still, do not replay
files from unknown sources.
"""

from __future__ import annotations

import base64
import builtins
import dataclasses
import enum
import functools
import hashlib
import io
import pickle
import sys
import time
from collections.abc import Iterator
from typing import Any

import numpy as np

SKIP_FIELDS = frozenset({"stats"})  # timings; everything else must be identical


def function_name(fn: Any) -> str:
    if isinstance(fn, functools.partial):
        kw = ", ".join(f"{k}={v!r}" for k, v in fn.keywords.items())
        return f"{function_name(fn.func)}({kw})" if kw else function_name(fn.func)
    return f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', repr(fn))}"


# -- fingerprints -------------------------------------------------------------------------------


def leaves(obj: Any, path: str = "result") -> Iterator[tuple[str, str]]:
    """(path, exact value) of every leaf, in a fixed order."""
    if obj is None or isinstance(obj, bool | int | str):
        yield path, repr(obj)
    elif isinstance(obj, float):
        yield path, obj.hex()
    elif isinstance(obj, np.ndarray):
        data = np.ascontiguousarray(obj).tobytes()
        yield path, f"{obj.dtype}{obj.shape}:{hashlib.sha256(data).hexdigest()[:24]}"
    elif isinstance(obj, np.generic):
        yield from leaves(obj.item(), path)
    elif isinstance(obj, enum.Enum):
        yield path, repr(obj)
    elif isinstance(obj, BaseException):
        yield path, f"{type(obj).__name__}: {obj}"
    elif dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        yield path, type(obj).__name__
        for f in dataclasses.fields(obj):
            if f.name not in SKIP_FIELDS:
                yield from leaves(getattr(obj, f.name), f"{path}.{f.name}")
    elif isinstance(obj, dict):
        yield path, f"dict of {len(obj)}"
        for k in sorted(obj, key=str):
            if k not in SKIP_FIELDS:
                yield from leaves(obj[k], f"{path}[{k!r}]")
    elif isinstance(obj, list | tuple):
        yield path, f"{type(obj).__name__} of {len(obj)}"
        for i, v in enumerate(obj):
            yield from leaves(v, f"{path}[{i}]")
    else:
        yield path, type(obj).__name__


def fingerprint(obj: Any) -> str:
    h = hashlib.sha256()
    for p, v in leaves(obj):
        h.update(f"{p}={v}\n".encode())
    return h.hexdigest()


def first_difference(recorded: Any, replayed: Any) -> str:
    a, b = list(leaves(recorded)), list(leaves(replayed))
    for (pa, va), (pb, vb) in zip(a, b, strict=False):
        if pa != pb or va != vb:
            return f"{pa}: recorded {va}, replayed {vb}" if pa == pb else f"recorded {pa} = {va}, replayed {pb} = {vb}"
    if len(a) != len(b):
        return f"recorded {len(a)} values, replayed {len(b)}"
    return "no difference found leaf by leaf"


def _trajectory(result: Any) -> Any:
    route = getattr(result, "route", None)
    return getattr(route, "trajectory", None) if route is not None else getattr(result, "trajectory", None)


def compiled_used(result: Any, default: bool) -> bool:
    """Whether the plan ran the compiled pass (its stats say; the two paths agree to rounding,
    not bit for bit), else `default` (where the call ran: [planner] compiled in a planner
    process; the service process never loads it)."""
    stats = getattr(_trajectory(result), "stats", None) or {}
    steps = stats.get("n_compiled_steps")
    return bool(steps) if isinstance(steps, int) else default


def _scalars(d: Any) -> dict[str, Any]:
    """The top-level numbers, strings and flags of a stats dictionary (the rest is in the pickle)."""
    if not isinstance(d, dict):
        return {}
    return {str(k): v for k, v in d.items() if v is None or isinstance(v, bool | int | float | str)}


def summary_of(result: Any) -> dict[str, Any]:
    """Readable fields of a planner result for the record: small on purpose (the writer thread
    must not hold the interpreter lock for long); the trajectory itself is on /out/trajectory
    once flown, and everything is in the pickled result."""
    if isinstance(result, BaseException):
        return {"ok": None, "status": "error", "message": f"{type(result).__name__}: {result}"}
    out: dict[str, Any] = {"ok": getattr(result, "ok", None)}
    status = getattr(result, "status", None)
    out["status"] = status.value if isinstance(status, enum.Enum) else (None if status is None else str(status))
    out["message"] = getattr(result, "message", None)
    out["stats"] = _scalars(getattr(result, "stats", None))
    traj = _trajectory(result)
    out["trajectory"] = None if traj is None else {
        "segments": int(traj.n_segments), "t0": float(traj.t0), "t_end": float(traj.t_end),
        "corridors": traj.corridors is not None, "stats": _scalars(traj.stats)}
    return out


# -- reading calls back -------------------------------------------------------------------------

_NUMPY = {
    ("numpy.core.multiarray", "_reconstruct"), ("numpy._core.multiarray", "_reconstruct"),
    ("numpy.core.multiarray", "scalar"), ("numpy._core.multiarray", "scalar"),
    ("numpy", "ndarray"), ("numpy", "dtype"), ("numpy.core.numeric", "_frombuffer"),
    ("numpy._core.numeric", "_frombuffer"),
}
_PLAIN = {
    ("copyreg", "_reconstructor"), ("copyreg", "__newobj__"), ("builtins", "object"), ("builtins", "set"),
    ("builtins", "frozenset"), ("builtins", "slice"), ("builtins", "complex"),
    ("functools", "partial"), ("collections", "OrderedDict"),
}


class _SafeUnpickler(pickle.Unpickler):
    def find_class(self, module: str, name: str) -> Any:
        if (module, name) in _PLAIN:
            return super().find_class(module, name)
        if (module, name) in _NUMPY or module.startswith("numpy.dtypes"):
            return super().find_class(module, name)
        if module.startswith(("planner_core", "companion")) and not module.startswith(
                ("planner_core.formats", "companion.__main__", "companion.cli_", "companion.service")):
            obj = super().find_class(module, name)
            if isinstance(obj, type) and (dataclasses.is_dataclass(obj) or issubclass(obj, enum.Enum | BaseException)):
                return obj
            if callable(obj) and not isinstance(obj, type) and (
                    module.startswith("planner_core") or module in ("companion.mission", "companion.route")):
                return obj  # a planner function: what a recorded call names
        if module == "builtins":
            obj = getattr(builtins, name, None)
            if isinstance(obj, type) and issubclass(obj, BaseException):
                return obj
        raise pickle.UnpicklingError(f"replay does not load {module}.{name} from a recording")


def loads(text: str) -> Any:
    return _SafeUnpickler(io.BytesIO(base64.b64decode(text))).load()


# -- the replay ---------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Replayed:
    seq: int
    function: str
    identical: bool
    recorded_ms: float
    replayed_ms: float
    difference: str = ""


def recorded_environment(path: str) -> dict[str, str]:
    import json

    from mcap.exceptions import McapError
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as fh:
            for m in make_reader(fh).iter_metadata():
                if m.name == "companion" and "environment" in m.metadata:
                    env: dict[str, str] = json.loads(m.metadata["environment"])
                    return env
    except (McapError, ValueError):  # no summary: no metadata index
        pass
    return {}


def plan_records(path: str, since: float | None = None, until: float | None = None) -> Iterator[dict[str, Any]]:
    """The /planner/plan records of a file; `since`/`until`: seconds from the recording's start."""
    import json

    from companion.recording import read_messages

    start = None
    for _schema, _channel, message in read_messages(path):  # the first message of any channel: t = 0
        if start is None:
            start = message.log_time
        if _channel.topic != "/planner/plan":
            continue
        rel = (message.log_time - start) / 1e9
        if since is not None and rel < since:
            continue
        if until is not None and rel > until:
            break
        yield json.loads(message.data)


def replay_one(rec: dict[str, Any]) -> Replayed:
    from planner_core import use_compiled_kernel

    name = rec["function"]
    if rec.get("call") is None:
        return Replayed(rec["seq"], name, False, rec.get("latency_ms", 0.0), 0.0, "the call was not recorded (not picklable)")
    fn, args = loads(rec["call"])
    # process-wide switch: borrowed for this call only, or a library user's later plans (and
    # the next test in the same process) would run as the recording did
    before = use_compiled_kernel(bool(rec.get("compiled")), "replay: as recorded")
    t0 = time.perf_counter()
    try:
        result: Any = fn(*args)
    except Exception as exc:
        result = exc
    finally:
        use_compiled_kernel(before is None, before or "")
    took = (time.perf_counter() - t0) * 1000
    if fingerprint(result) == rec["fingerprint"]:
        return Replayed(rec["seq"], name, True, rec.get("latency_ms", 0.0), took)
    if rec.get("result") is not None:
        recorded = loads(rec["result"])
        if fingerprint(recorded) == fingerprint(result):
            # the recording predates a field added to a result type since: read back, that field
            # takes its default, and every value the recording holds is reproduced
            return Replayed(rec["seq"], name, True, rec.get("latency_ms", 0.0), took)
        why = first_difference(recorded, result)
    else:
        why = f"recorded {rec.get('message')!r}, replayed {summary_of(result).get('message')!r}"
    return Replayed(rec["seq"], name, False, rec.get("latency_ms", 0.0), took, why)


def main(argv: list[str]) -> int:
    import argparse

    from mcap.exceptions import McapError

    p = argparse.ArgumentParser(prog="python -m companion replay", description=__doc__.splitlines()[0])
    p.add_argument("file")
    p.add_argument("--from", dest="since", type=float, default=None, metavar="T",
                   help="seconds from the start of the recording")
    p.add_argument("--until", type=float, default=None, metavar="T")
    p.add_argument("--keep-going", action="store_true", help="replay every plan, not only up to the first difference")
    args = p.parse_args(argv)
    n = bad = 0
    try:
        from companion.recorder import environment

        here, there = environment(), recorded_environment(args.file)
        differ = {k: (there.get(k), v) for k, v in here.items() if k in there and there[k] != v}
        if differ:
            print("note: recorded on another environment (" + ", ".join(f"{k} {a} here {b}" for k, (a, b)
                  in differ.items()) + "): its numerical kernels may round differently", flush=True)
        for rec in plan_records(args.file, args.since, args.until):
            r = replay_one(rec)
            n += 1
            mark = "identical" if r.identical else "DIFFERS"
            print(f"plan {r.seq:4d} {r.function}: {mark} (recorded {r.recorded_ms:.1f} ms, "
                  f"replayed {r.replayed_ms:.1f} ms)", flush=True)
            if not r.identical:
                bad += 1
                print(f"  first difference: {r.difference}")
                if not args.keep_going:
                    break
    except (OSError, ValueError, KeyError, pickle.UnpicklingError, McapError) as exc:
        print(f"replay: {args.file}: {exc}", file=sys.stderr)
        return 2
    if n == 0:
        print("replay: no plan in the recording (or in the time range)", file=sys.stderr)
        return 2
    print(f"{n - bad} of {n} plans reproduced bit-identically" if bad == 0 or args.keep_going
          else f"plan {n}: the first that differs")
    return 0 if bad == 0 else 1
