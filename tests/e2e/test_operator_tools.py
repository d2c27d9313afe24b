"""`python -m companion send` / `watch` never report success for nothing: distinct exit codes
for no answer, a rejection, a refusal by the companion and a denial by the autopilot;
`--wait-for STATE`; `watch` says when it hears nothing."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from e2e_rig import REPO, VEHICLE, Rig

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def rig(rig_factory: Any) -> Rig:
    r: Rig = rig_factory("px4")
    return r


def cli(rig: Rig, *args: str, stdin: str | None = None, timeout: float = 60) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "companion", *args, "--connect", f"tcp/127.0.0.1:{rig.zport}"],
                          capture_output=True, text=True, timeout=timeout, cwd=REPO, input=stdin)


def send(rig: Rig, key: str, body: dict[str, Any], *extra: str, vehicle: str = VEHICLE) -> subprocess.CompletedProcess[str]:
    return cli(rig, "send", key, "-", "--vehicle", vehicle, *extra, stdin=json.dumps(body))


def events(out: subprocess.CompletedProcess[str]) -> list[dict[str, Any]]:
    return [json.loads(line) for line in out.stdout.splitlines() if line.startswith("{")]


def test_nobody_answers(rig: Rig) -> None:
    out = send(rig, "command", {"command": "arm"}, "--wait", "2", vehicle="nobody")
    assert out.returncode == 3, out
    assert "no companion answered" in out.stderr


def test_rejected_message(rig: Rig) -> None:
    out = send(rig, "command", {"command": "loop"}, "--wait", "5")
    assert out.returncode == 1, out
    assert any(e["type"] == "rejected" for e in events(out))


def test_refused_by_the_companion(rig: Rig) -> None:
    out = send(rig, "command", {"command": "disarm"}, "--wait", "5")  # already disarmed
    assert out.returncode == 4, out
    assert any(e["type"] == "refused" and e.get("by") == "companion" for e in events(out))


def test_denied_by_the_autopilot(rig: Rig) -> None:
    mode = rig.control.state()["mode"]
    assert rig.control.reject_arming(True)["ok"]
    try:
        out = send(rig, "command", {"command": "arm"}, "--wait", "20")
    finally:
        assert rig.control.reject_arming(False)["ok"]
    assert out.returncode == 5, out
    seen = events(out)
    assert any(e["type"] == "accepted" for e in seen)  # accepted first: not a success on its own
    assert any(e["type"] == "refused" and e.get("by") == "autopilot" for e in seen)
    rig.wait_status(lambda s: s["mode"] == mode and s["state"] == "IDLE", 10, f"back in {mode}")


def test_completed_and_wait_for_state(rig: Rig) -> None:
    out = send(rig, "command", {"command": "arm"}, "--wait", "20", "--wait-for", "READY")
    assert out.returncode == 0, out
    assert any(e["type"] == "completed" and e.get("command") == "arm" for e in events(out))
    assert rig.statuses[-1]["state"] == "READY" and rig.statuses[-1]["armed"]
    # a state that does not come within --wait
    out = send(rig, "command", {"command": "hold"}, "--wait", "3", "--wait-for", "STREAMING")
    assert out.returncode in (4, 6), out  # on the ground: refused (4); were it taken: not reached (6)
    out = send(rig, "command", {"command": "disarm"}, "--wait", "10", "--wait-for", "IDLE")
    assert out.returncode == 0, out


def test_watch_says_when_it_hears_nothing(rig: Rig, tmp_path: Path) -> None:
    out = cli(rig, "watch", "--vehicle", "nobody", "--duration", "3", "--silence", "1")
    assert out.returncode == 0 and "nothing heard from vehicle 'nobody'" in out.stderr, out
    out = cli(rig, "watch", "--vehicle", VEHICLE, "--duration", "3", "--silence", "1")
    assert "nothing heard" not in out.stderr and "status " in out.stdout
    out = cli(rig, "watch", "--vehicle", VEHICLE, "--duration", "10", "--wait-for", "IDLE")
    assert out.returncode == 0
    out = cli(rig, "watch", "--vehicle", VEHICLE, "--duration", "2", "--wait-for", "STREAMING")
    assert out.returncode == 6
