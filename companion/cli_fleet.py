"""`python -m companion fleet`: the vehicles present (liveliness), each with its state,
mission, progress and clock offset (its status, checked as `send` checks it)."""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import time
from typing import Any

from companion.cli_client import EXIT_NO_ANSWER, Origin, client_session


def fleet_list(session: Any, prefix: str, timeout: float = 1.0) -> list[dict[str, Any]]:
    """The vehicles present (a liveliness token at `<prefix>/<vehicle>/alive`), each with the
    status its companion answers (`<prefix>/<vehicle>/status`, checked as `send` checks it: the
    exact key, one session whose id is in the body), in vehicle order."""
    from companion.wire.keys import ALIVE

    present: set[str] = set()
    with contextlib.suppress(Exception):
        for reply in session.liveliness().get(f"{prefix}/*/{ALIVE}", timeout=timeout):
            if reply.ok is None:
                continue
            parts = str(reply.ok.key_expr).split("/")
            if len(parts) == len(prefix.split("/")) + 2 and parts[-1] == ALIVE:
                present.add(parts[-2])
    out: list[dict[str, Any]] = []
    for vehicle in sorted(present):
        base = f"{prefix}/{vehicle}"
        status: dict[str, Any] | None = None
        clock: tuple[float, float] | None = None
        origin = Origin(session, base, timeout=timeout)
        if origin.companion is not None:
            with contextlib.suppress(Exception):
                asked = time.time()
                for reply in session.get(f"{base}/status", timeout=timeout):
                    answered = time.time()
                    if reply.ok is None or str(reply.ok.key_expr) != f"{base}/status":
                        continue
                    body = json.loads(reply.ok.payload.to_bytes())
                    if isinstance(body, dict) and body.get("session") == origin.companion:
                        status = body
                        # the status is made when asked: its `time` (the vehicle's clock, ms) against
                        # the middle of the round trip here, give or take half of it
                        if isinstance(body.get("time"), int | float):
                            half = (answered - asked) / 2.0
                            clock = (float(body["time"]) - (asked + half), half + 0.0005)
                        break
        out.append({"vehicle": vehicle, "status": status, "note": None if status is not None else origin.note,
                    "clock_offset_ms": None if clock is None else round(clock[0] * 1000.0, 1),
                    "clock_uncertainty_ms": None if clock is None else round(clock[1] * 1000.0, 1)})
    return out


FLEET_COLUMNS = ("vehicle", "state", "mission", "progress", "armed", "link", "frame", "clock_ms")


def _fleet_row(entry: dict[str, Any]) -> dict[str, Any]:
    st = entry["status"] or {}
    fleet = st.get("fleet") if isinstance(st.get("fleet"), dict) else {}
    return {"vehicle": entry["vehicle"], "state": st.get("state", "?"), "mission": st.get("mission"),
            "progress": st.get("progress"), "armed": st.get("armed"), "link": st.get("link"),
            "frame": fleet.get("frame") if fleet else None, "clock_ms": entry.get("clock_offset_ms")}


def clock_warning(entry: dict[str, Any]) -> str | None:
    """The vehicle's clock is off this computer's by more than its `[fleet] clock_tolerance`
    (beyond what the round trip leaves unknown): what to say, else None."""
    st = entry["status"] or {}
    fleet = st.get("fleet") if isinstance(st.get("fleet"), dict) else None
    off, unsure = entry.get("clock_offset_ms"), entry.get("clock_uncertainty_ms")
    if fleet is None or off is None or unsure is None or not isinstance(fleet.get("clock_tolerance"), int | float):
        return None
    tolerance_ms = float(fleet["clock_tolerance"]) * 1000.0
    if abs(off) - unsure <= tolerance_ms:
        return None
    return (f"{entry['vehicle']}: its clock is {off:+.0f} ms (+-{unsure:.0f}) off this computer's, more than its "
            f"[fleet] clock_tolerance ({tolerance_ms:.0f} ms): check NTP/chrony/PTP on both")


def cmd_fleet(args: argparse.Namespace) -> int:
    """List the vehicles present (liveliness) with their state, mission and progress (status).
    Exit 0 when at least one vehicle is present, 3 when none is."""
    session = client_session(args, args.wait)
    try:
        deadline = time.monotonic() + args.wait
        while True:
            entries = fleet_list(session, args.prefix, timeout=min(1.0, max(args.wait, 0.1)))
            if entries or time.monotonic() >= deadline:
                break
            time.sleep(0.2)
    finally:
        session.close()
    if args.json:
        for e in entries:
            print(json.dumps({**_fleet_row(e), "clock_uncertainty_ms": e.get("clock_uncertainty_ms"),
                              "status": e["status"], "note": e["note"]}), flush=True)
    else:
        rows = [[_cell(v, k) for k, v in _fleet_row(e).items()] for e in entries]
        widths = [max([len(c)] + [len(r[i]) for r in rows]) for i, c in enumerate(FLEET_COLUMNS)]
        print("  ".join(c.ljust(w) for c, w in zip(FLEET_COLUMNS, widths, strict=True)).rstrip())
        for r in rows:
            print("  ".join(c.ljust(w) for c, w in zip(r, widths, strict=True)).rstrip())
    for e in entries:
        if e["note"] and not args.json:
            print(f"fleet: {e['vehicle']}: {e['note']}", file=sys.stderr)
        warning = clock_warning(e)
        if warning is not None:
            print(f"fleet: {warning}", file=sys.stderr)
    if not entries:
        print(f"fleet: no vehicle present under {args.prefix}/*/alive within {args.wait:g} s (--prefix and "
              "--connect must match the fleet's router or companions)", file=sys.stderr)
        return EXIT_NO_ANSWER
    return 0


def _cell(v: Any, column: str) -> str:
    if v is None:
        return "-"
    if isinstance(v, bool):
        return "yes" if v else "no"
    if column == "progress" and isinstance(v, int | float):
        return f"{v:.0%}"
    if column == "clock_ms" and isinstance(v, int | float):
        return f"{v:+.0f}"
    return str(v)
