"""The README's five-minute walkthrough, run as written (issue 20.7, 22.6).

The fenced block marked ```sh walkthrough in README.md is run verbatim by bash with `-e`, so
a command that fails (a `send` that is refused, a `watch` that times out, a file that does not
exist) fails this test. `python` is this interpreter; the working directory is the clone. The
walkthrough uses the defaults (the mock's PX4-SITL port pair, the companion's
udpin:127.0.0.1:14540 and tcp/127.0.0.1:7447), so it runs in a network namespace of its own
(`unshare -rn`: fresh loopback, no clash with anything else on the machine) where the kernel
allows one, else directly when those ports are free.
"""

from __future__ import annotations

import contextlib
import os
import re
import shutil
import signal
import socket
import subprocess
import sys
from pathlib import Path

import pytest

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
FENCE = re.compile(r"^```sh walkthrough\n(.*?)^```", re.MULTILINE | re.DOTALL)


def walkthrough(readme: str) -> str:
    found = FENCE.findall(readme)
    assert len(found) == 1, "README.md must hold exactly one ```sh walkthrough block"
    return str(found[0])


def _own_netns() -> bool:
    if shutil.which("unshare") is None or shutil.which("ip") is None:
        return False
    probe = subprocess.run(["unshare", "-rn", "ip", "link", "set", "lo", "up"], capture_output=True)
    return probe.returncode == 0


def _defaults_free() -> bool:
    for kind, port in ((socket.SOCK_DGRAM, 14540), (socket.SOCK_DGRAM, 14580), (socket.SOCK_STREAM, 7447)):
        with socket.socket(socket.AF_INET, kind) as s:
            try:
                s.bind(("127.0.0.1", port))
            except OSError:
                return False
    return True


def test_the_walkthrough_covers_the_first_hour() -> None:
    readme = (REPO / "README.md").read_text()
    assert len(readme.splitlines()) <= 200, "the README is a ten-minute read: the rest goes to docs/"
    script = walkthrough(readme)
    steps = [line.split("#")[0].strip() for line in script.splitlines() if line.split("#")[0].strip()]
    # mock + companion with their defaults, send/watch, a mission, a pop-up, land
    assert steps[0] == "python -m sitl_mock &" and steps[1] == "python -m companion run &", steps[:2]
    for needed in ("send mission", "send obstacles", "examples/land.json", "watch"):
        assert any(needed in s for s in steps), needed
    for path in re.findall(r"examples/\S+\.json", script):
        assert (REPO / path).is_file(), path


def test_the_readme_walkthrough_runs_as_written(tmp_path: Path) -> None:
    script = walkthrough((REPO / "README.md").read_text())
    (tmp_path / "walkthrough.sh").write_text(script)
    bindir = tmp_path / "bin"
    bindir.mkdir()
    (bindir / "python").write_text(f'#!/bin/sh\nexec "{sys.executable}" "$@"\n')
    (bindir / "python").chmod(0o755)
    env = {**os.environ, "PATH": f"{bindir}:{os.environ['PATH']}", "PYTHONPATH": str(REPO),
           "PYTHONUNBUFFERED": "1"}
    run = ["bash", "-e", str(tmp_path / "walkthrough.sh")]
    if _own_netns():
        cmd = ["unshare", "-rn", "bash", "-c", f'ip link set lo up && exec {" ".join(run)}']
    elif _defaults_free():
        cmd = run
    else:
        pytest.skip("no network namespace (unshare -rn) and the default ports 14540/14580/7447 are in use")
    out = tmp_path / "out.txt"
    with open(out, "wb") as fh:
        proc = subprocess.Popen(cmd, cwd=REPO, env=env, stdout=fh, stderr=subprocess.STDOUT, start_new_session=True)
        try:
            code = proc.wait(420)
        except subprocess.TimeoutExpired:
            code = None
        finally:
            with contextlib.suppress(ProcessLookupError):
                os.killpg(proc.pid, signal.SIGKILL)  # what the script left running, if it failed
    text = out.read_text(errors="replace")
    tail = "\n".join(line for line in text.splitlines() if "setpoint gap" not in line)[-4000:]
    assert code == 0, f"the walkthrough failed (exit {code}):\n{tail}"
    # it did what the README says: a mission flown, a pop-up acted on, a landing on the ground
    assert '"mission": "walkthrough"' in text and '"added": ["crane"]' in text, tail
    assert re.search(r"companion INFO (replanned|braking): ", text), tail  # the companion's log (stderr)
    assert re.search(r'"type": "completed".*"command": "land"', text), tail
