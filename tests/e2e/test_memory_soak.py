"""Memory given back (issue 21.5): after big missions are planned and replaced, obstacles added
and removed, the companion's main process returns to within ~10 MB of its idle figure.

Over a campaign of big missions and removals the main process had grown 121 -> 222 MB and never
shrunk: glibc keeps the pages a big plan freed for reuse. The companion process runs as in the
field (`python -m companion run`, planner processes, the setpoint process) against the mock.
Two missions of 200 waypoints here (the planning happens in the planner processes, so the main
process shows the regrowth as soon as it keeps what a plan freed); the long soak and its figures
are `benchmarks/service.py --loaded` (RSS idle and after the soak).
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from e2e_rig import Rig

SOAK = 2
WAYPOINTS = 200
REGROWTH_MB = 10.0


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return float(line.split()[1]) / 1024
    raise AssertionError("no VmRSS")


def _big(i: int) -> dict[str, object]:
    rng = np.random.default_rng(i)
    steps = rng.normal(size=(WAYPOINTS - 1, 3)) * [1.5, 1.5, 0.2]
    wps = np.cumsum(np.vstack([[-10.0, -10.0, -3.0], steps]), axis=0)
    wps[:, :2] = np.clip(wps[:, :2], -18.0, 18.0)
    wps[:, 2] = np.clip(wps[:, 2], -6.0, -2.0)
    # checked and kept pending: the planning load without flying it
    return {"id": f"soak-{i}", "frame": "ned", "autostart": False, "waypoints": wps.round(3).tolist()}


def _settled_rss(pid: int, seconds: float = 4.0) -> float:
    """The lowest RSS over a few seconds (the companion hands its heap back ~2 s after a plan)."""
    end, low = time.monotonic() + seconds, float("inf")
    while time.monotonic() < end:
        low = min(low, _rss_mb(pid))
        time.sleep(0.2)
    return low


def test_memory_returns_to_idle_after_big_missions_and_removals(tmp_path: Path) -> None:
    rig = Rig("px4", tmp_path)
    rig.start()
    try:
        pid = rig.procs[1].pid
        rig.ensure_airborne()
        # idle: warmed up, one small mission planned and kept (as after the soak)
        since = rig.mark()
        rig.put("mission", {"id": "small", "frame": "ned", "autostart": False,
                            "waypoints": [[1.0, 1.0, -2.0], [2.0, 1.0, -2.0], [2.0, 2.0, -2.0]]})
        rig.wait_event(lambda e: e.get("key") == "mission" and e["type"] in ("accepted", "rejected"), 60,
                       "the small mission's answer", since)
        idle = _settled_rss(pid)
        peak = idle
        for i in range(SOAK):
            since = rig.mark()
            rig.put("mission", _big(i))
            answer = rig.wait_event(lambda e: e.get("key") == "mission" and e["type"] in ("accepted", "rejected"),
                                    240, f"mission soak-{i}'s answer", since)
            assert answer["type"] == "accepted", answer
            peak = max(peak, _rss_mb(pid))
            ids = [f"o{i}-{k}" for k in range(40)]
            rig.put("obstacles", {"add": [{"id": n, "vertices": [[15.0 + dx, -15.0 + k * 0.3 + dy, -3.0 + dz]
                                                                  for dx in (0, 0.2) for dy in (0, 0.2)
                                                                  for dz in (0, 0.2)]}
                                          for k, n in enumerate(ids)]})
            time.sleep(0.5)
            rig.put("obstacles", {"remove": ids})
        since = rig.mark()
        rig.put("mission", {"id": "small-again", "frame": "ned", "autostart": False,
                            "waypoints": [[1.0, 1.0, -2.0], [2.0, 1.0, -2.0], [2.0, 2.0, -2.0]]})
        rig.wait_event(lambda e: e.get("key") == "mission" and e["type"] in ("accepted", "rejected"), 60,
                       "the last small mission's answer", since)
        after = _settled_rss(pid)
        print(f"main RSS: idle {idle:.0f} MB, peak {peak:.0f} MB during {SOAK} missions of {WAYPOINTS} waypoints, "
              f"after {after:.0f} MB")
        assert peak > idle, "the soak did not load the process"
        assert after <= idle + REGROWTH_MB, f"main RSS {idle:.0f} -> {after:.0f} MB after the soak"
    finally:
        rig.stop()
