"""Smoke test of `python -m companion demo --quick`: the whole chain flies one short mission.

Real processes (mock autopilot, companion service), a real Zenoh peer on loopback, real MAVLink
over UDP. The demo itself judges the flight; this test checks its verdict and the numbers behind
it, so a demo that printed OK on a bad flight would fail here too.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def test_quick_demo_flies_and_reports(tmp_path: Path) -> None:
    out = tmp_path / "demo"
    proc = subprocess.run(
        [sys.executable, "-m", "companion", "demo", "--quick", "--out", str(out), "--timeout", "90"],
        capture_output=True,
        text=True,
        timeout=150,
        cwd=ROOT,
    )
    report = proc.stdout + proc.stderr
    assert proc.returncode == 0, report[-4000:]
    summary = json.loads((out / "summary.json").read_text())
    assert summary["ok"] is True
    (mission,) = summary["missions"]
    assert mission["result"] == "OK"
    assert mission["verified"] == "True"
    rms, worst = (float(x) for x in mission["tracking error RMS / max"].removesuffix(" m").split(" / "))
    assert 0.0 < rms <= worst <= 1.0, report[-2000:]
    # what reached the mock is the planned trajectory, sampled (float32 on the wire)
    assert float(mission["setpoints vs trajectory, max"].removesuffix(" m")) < 1e-3
    for key in ("peak |v| planned / bound", "peak |a| planned / bound"):
        peak, bound = (float(x) for x in mission[key].split(" / "))
        assert 0.0 < peak <= bound
    for png in ("quick_path.png", "quick_derivatives.png"):
        assert (out / png).stat().st_size > 10_000
    log = [json.loads(line) for line in (out / "flight.jsonl").read_text().splitlines() if line.strip()]
    assert any(r["type"] == "setpoint" and r.get("applied") for r in log)
