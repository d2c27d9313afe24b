"""What a recorded call is reduced to, shared by the recorder that writes it and the replay that
checks it: a function's name, a result's leaves and fingerprint (every array bit for bit, every
number by its binary value, timings left out), a plan's or an inbound read's readable summary,
and the environment a bit-identical replay depends on.
"""

from __future__ import annotations

import contextlib
import dataclasses
import enum
import functools
import hashlib
from collections.abc import Iterator
from typing import Any

import numpy as np

SKIP_FIELDS = frozenset({"stats"})  # timings; everything else must be identical


def function_name(fn: Any) -> str:
    if isinstance(fn, functools.partial):
        kw = ", ".join(f"{k}={v!r}" for k, v in fn.keywords.items())
        return f"{function_name(fn.func)}({kw})" if kw else function_name(fn.func)
    return f"{getattr(fn, '__module__', '?')}.{getattr(fn, '__qualname__', repr(fn))}"


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


def first_difference(recorded: Any, replayed: Any, root: str = "result",
                     names: tuple[str, str] = ("recorded", "replayed")) -> str:
    """The first leaf (in `leaves` order) where the two differ, said as `names` say them."""
    ra, rb = names
    a, b = list(leaves(recorded, root)), list(leaves(replayed, root))
    for (pa, va), (pb, vb) in zip(a, b, strict=False):
        if pa != pb or va != vb:
            return f"{pa}: {ra} {va}, {rb} {vb}" if pa == pb else f"{ra} {pa} = {va}, {rb} {pb} = {vb}"
    if len(a) != len(b):
        return f"{ra} {len(a)} values, {rb} {len(b)}"
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


def decoded_summary(result: Any) -> dict[str, Any]:
    """What an inbound message became, readable: ok, the class, and a refusal's field and reason."""
    if isinstance(result, BaseException):
        return {"ok": False, "type": type(result).__name__, "field": getattr(result, "field", None),
                "reason": getattr(result, "reason", str(result))}
    return {"ok": True, "type": type(result).__name__, "field": None, "reason": None}


def decoded_fingerprint(result: Any) -> str:
    """A typed message by its every value; a refusal by its class, field and reason."""
    if isinstance(result, BaseException):
        return fingerprint(("refused", type(result).__name__, getattr(result, "field", None),
                            getattr(result, "reason", str(result))))
    return fingerprint(result)


def environment() -> dict[str, str]:
    """What a bit-identical replay depends on besides the recorded inputs: the interpreter, the
    numerical libraries and the machine (their kernels may round differently elsewhere)."""
    import platform
    from importlib import metadata

    env = {"python": platform.python_version(), "machine": platform.machine(), "system": platform.system()}
    for dist in ("numpy", "scipy", "daqp", "osqp", "numba"):
        with contextlib.suppress(metadata.PackageNotFoundError):
            env[dist] = metadata.version(dist)
    return env
