"""Issue 20: on PX4 SIH (9ececfdd) a SIGTERM at 2.89 m/s took 8.76 s of the 9.5 s `exit_timeout`
to hand over: the braking waited for the estimate under `[safety] rest_speed` (0.2 m/s), which
PX4's estimate rarely reaches. PX4's hold profile waits for its own rest speed (0.7 m/s), judged
from its lag (0.35 s) past the verified stop's end: against
the PX4 mock as PX4 SIH responds (0.3 s lag, its estimate straying in OFFBOARD and AUTO.LOITER),
the hand-over from ~3 m/s leaves at least 2 s of `exit_timeout`, the vehicle is slow when
AUTO.LOITER takes over, and the hold is still confirmed by watching it. In process: the service
stopped as SIGTERM stops it (`requested`), timed from the request to `run()`'s return."""

from __future__ import annotations

import asyncio
import json
import time
from pathlib import Path

import numpy as np
from companionkit import Events, service_for, until, up

from companion.handover import HOLD_PROFILES
from companion.wire.messages import MissionSpec, read
from sitl_mock import MockAutopilot, MockConfig
from sitl_mock.vehicle import RESPONSES

MARGIN = 2.0  # s of exit_timeout left (systemd's TimeoutStopSec is 10 s, PX4's exit_timeout 9.5 s)
# one long diagonal leg, 2 m above home: at ~3 m/s in its middle (the default bounds are per axis,
# planned within 80 % of them)
MISSION = b'{"id": "leg", "origin": "home", "waypoints": [[25, 25, -2]]}'


def test_px4_hand_over_from_3_m_s_leaves_a_margin_to_exit_timeout(tmp_path: Path) -> None:
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"], vehicle=RESPONSES["px4_sih"],
                                    log_path=str(tmp_path / "f.jsonl"), log_rate_hz=50)).start()

    async def fly() -> tuple[bool, float, float, Events]:
        svc = service_for(mock)
        events = Events(svc)
        st = svc.link.state
        task = asyncio.create_task(svc.run())
        await up(svc, task)
        await until(lambda: st.position_problem() is None and st.home is not None, 10, "position and home")
        await svc.commands.takeoff(2.0)
        spec = read("mission", MISSION, svc.cfg, st.home, autopilot=st.autopilot)
        assert isinstance(spec, MissionSpec), spec
        for attempt in range(3):  # a loaded test machine may plan too late for the split: sent again
            seen = len(events.all)
            await svc.navigator.on_mission(spec, time.monotonic())
            answers = [e for e in events.all[seen:] if e["type"] in ("accepted", "rejected") and e.get("key") == "mission"]
            assert answers, events.all[seen:]
            if answers[-1]["type"] == "accepted":
                break
            assert "after the split time" in answers[-1]["message"] and attempt < 2, answers[-1]
        try:
            await until(lambda: float(np.linalg.norm(mock.snapshot()["velocity"])) >= 2.8, 20, "~3 m/s")
        except AssertionError as exc:  # say what the mission did instead
            raise AssertionError(f"{exc}; events {[(e['type'], e['message']) for e in events.all[-8:]]}") from exc
        speed = float(np.linalg.norm(mock.snapshot()["velocity"]))
        t0 = time.monotonic()
        svc.requested.set()  # what SIGTERM does (companion.cli_run)
        handed_over = bool(await asyncio.wait_for(task, 30))
        return handed_over, time.monotonic() - t0, speed, events

    try:
        handed_over, took, speed, events = asyncio.run(fly())
    finally:
        mock.stop()
    last = events.of("handover")[-1]
    assert handed_over is True and last["held"] is True and last["mode"] == "LOITER", last
    assert speed >= 2.8
    budget = HOLD_PROFILES["px4"].exit_timeout
    assert took <= budget - MARGIN, f"the hand-over took {took:.2f} s of {budget} s"
    assert last["limits"]["rest_speed"] == HOLD_PROFILES["px4"].rest_speed
    # braked by our verified stop first: the vehicle itself (the mock's truth) has nearly stopped
    # when AUTO.LOITER takes over (as tests/e2e/test_lifecycle.py asks), though its estimate may
    # read up to the rest speed
    log = [json.loads(line) for line in (tmp_path / "f.jsonl").read_text().splitlines() if line.strip()]
    t_hand = next(r["t"] for r in log if r["type"] == "mode" and r.get("to") == "LOITER" and r["reason"] == "command")
    at_hand = [r for r in log if r["type"] == "state" and t_hand - 0.05 <= r["t"]][:5]
    assert at_hand and max(float(np.linalg.norm(r["vel"])) for r in at_hand) <= 0.3, at_hand
