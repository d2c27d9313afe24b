"""Flight log: JSON Lines, one record per state sample, setpoint, mode change or event."""

from __future__ import annotations

import json
import math
import threading
import time
from pathlib import Path
from typing import Any, TextIO

import numpy as np


def _clean(value: Any) -> Any:
    """JSON has no NaN: write null for axes that were not commanded."""
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float):
        return value if math.isfinite(value) else None
    if isinstance(value, (list, tuple)):
        return [_clean(v) for v in value]
    if isinstance(value, dict):
        return {k: _clean(v) for k, v in value.items()}
    return value


class FlightLog:
    def __init__(self, path: str | Path | None, flush_interval_s: float = 0.5) -> None:
        self.path = Path(path) if path else None
        self._fh: TextIO | None = open(self.path, "w", encoding="utf-8") if self.path else None  # noqa: SIM115
        self._buf: list[str] = []
        self._lock = threading.Lock()
        self._flush_interval = flush_interval_s
        self._last_flush = time.monotonic()

    def write(self, record_type: str, t: float, **fields: Any) -> None:
        if self._fh is None:
            return
        rec = {"type": record_type, "t": round(t, 6), **fields}
        line = json.dumps(_clean(rec), separators=(",", ":"))
        with self._lock:
            self._buf.append(line)
        if time.monotonic() - self._last_flush >= self._flush_interval:
            self.flush()

    def flush(self) -> None:
        with self._lock:
            if self._fh is None:
                return
            if self._buf:
                self._fh.write("\n".join(self._buf) + "\n")
                self._buf.clear()
            self._fh.flush()
            self._last_flush = time.monotonic()

    def close(self) -> None:
        self.flush()
        with self._lock:
            if self._fh is not None:
                self._fh.close()
                self._fh = None


def read_log(path: str | Path) -> list[dict[str, Any]]:
    with open(path, encoding="utf-8") as fh:
        return [json.loads(line) for line in fh if line.strip()]
