"""The companion against the PX4 flavour as PX4 1.15 behaves (issue 15), one stateful flight:
the ground at local z = +1.6 with HOME_POSITION to match, EVENT messages instead of
STATUSTEXT, an arming refusal, a takeoff above the ground, a home-relative mission, then a
stall of the companion's own event loop long enough for PX4's offboard-loss fallback (land
and disarm). The companion must say the companion (not the link) stalled, send no setpoint
from the stall on (so PX4 never re-enters OFFBOARD on one), and follow PX4 out of FAILSAFE."""

from __future__ import annotations

import asyncio
import time
from pathlib import Path

import numpy as np
from companionkit import Events, service_for, serving, until

from companion.wire.messages import Command, MissionSpec, read
from sitl_mock import MockAutopilot, MockConfig

LIMIT = 0.5  # s: [setpoints] loop_stall_limit here (1.5 s by default)
# s: the setpoints stop at LIMIT, PX4's COM_OF_LOSS_T (1 s) runs out well before the loop wakes (at
# LIMIT + 1.5 a loaded CI run saw the loop wake first: its hold request put the vehicle in LOITER
# before the failsafe, as it would on PX4, and nothing landed it)
STALL = LIMIT + 5.0  # (LIMIT + 3.0: the same once more in CI, session 16: the mock, stepping late on a loaded runner)


def test_px4_ground_events_refusal_home_mission_and_a_companion_stall(tmp_path: Path) -> None:
    # COM_OBL_RC_ACT 4: land on offboard loss (PX4's no-RC fallback ends on the ground too)
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"], params={"COM_OBL_RC_ACT": 4},
                                    log_path=str(tmp_path / "f.jsonl"))).start()
    ground = mock.ground_z

    async def go() -> None:
        svc = service_for(mock, safety={"auto_arm": True, "takeoff_altitude": 1.0},
                          setpoints={"loop_stall_limit": LIMIT})
        events = Events(svc)
        st = svc.link.state
        async with serving(svc):
            await until(lambda: st.home is not None and st.position_problem() is None, 10, "home and position")
            assert ground > 1.0 and abs(st.home[2] - ground) < 0.05  # type: ignore[index]
            status = svc.status()
            assert status["home"] is not None and status["origin"] == "local"
            assert status["mode"] == "LOITER" and status["active_mode"] is None  # PX4's boot mode, disarmed

            # 1. an arming refusal: the result code and PX4's EVENT, not a STATUSTEXT
            mock.reject_arming = True
            await svc.commands.on_command(Command("arm"), time.monotonic())
            await until(lambda: events.of("refused"), 10, "the refusal")
            refused = events.of("refused")[0]
            assert refused["by"] == "autopilot" and refused["result"] == "MAV_RESULT_TEMPORARILY_REJECTED"
            assert refused["event"]["id"] > 0 and refused["event"]["level"] == "ERROR", refused
            relayed = [e for e in events.of("autopilot") if e.get("source") == "event"]
            assert any(e["event_id"] == refused["event"]["id"] for e in relayed)
            assert not [e for e in events.of("autopilot") if e.get("source") == "statustext"]
            assert st.mode == "LOITER"  # back in the mode it was in

            # 2. takeoff: 1 m above the ground where it stands, not z = -1 in the local frame
            mock.reject_arming = False
            await svc.commands.on_command(Command("takeoff", 1.0), time.monotonic())
            try:
                await until(lambda: svc.flight.state.value == "READY" and svc.flight.airborne, 30, "airborne")
            except AssertionError:
                raise AssertionError([(e["type"], e["message"]) for e in events.all][-10:]) from None
            assert abs(st.position[2] - (ground - 1.0)) < 0.25, st.position

            # 3. a home-relative mission: 1.5 m above home
            spec = read("mission", b'{"id": "rel", "origin": "home", "waypoints": [[1.5, 0.0, -1.5]]}', svc.cfg,
                        st.home)
            assert isinstance(spec, MissionSpec)
            await svc.navigator.on_mission(spec, time.monotonic())
            await until(lambda: events.of("mission_complete"), 20, "the mission")
            await until(lambda: float(np.linalg.norm(st.velocity)) < 0.2, 10, "at rest")
            np.testing.assert_allclose(st.position, st.home + np.array([1.5, 0.0, -1.5]), atol=0.25)  # type: ignore[operator]

            # 4. the companion's own loop stalls (a blocking call on it). The report names the state
            # as of the liveness loop's last beat (every setpoint period): let it beat in HOLDING
            # first (a fast plan is at rest as soon as it completes)
            await asyncio.sleep(0.2)
            before = len(events.all)
            t_stall = time.monotonic()
            time.sleep(STALL)
            await until(lambda: events.of("stalled"), 5, "the stall report")
            ev = events.of("stalled")[0]
            assert ev["cause"] == "companion" and ev["stall_ms"] >= 1000 * LIMIT and ev["previous_state"] == "HOLDING"
            assert ev["setpoints_withheld"] is True
            # no setpoint sampled once the loop had been silent for the limit
            assert svc.control.last_sp_time <= t_stall + svc.cfg.setpoints.loop_stall_limit
            sent = svc.link.sent_setpoints
            assert svc.flight.state.value == "FAILSAFE"
            # PX4 lands and disarms by itself; nothing re-enters OFFBOARD; the companion follows
            while svc.flight.state.value != "IDLE":
                assert not (st.armed and st.mode == "OFFBOARD"), "the autopilot re-entered OFFBOARD"
                assert time.monotonic() - t_stall < 30, f"not IDLE: {svc.flight.state} {st.mode} {st.armed}"
                await asyncio.sleep(0.05)
            assert svc.link.sent_setpoints == sent and not st.armed
            after = events.all[before:]
            kinds = [e["type"] for e in after]
            assert "link_lost" not in kinds and "pilot_takeover" not in kinds, after
            assert any(e["type"] == "failsafe" and e.get("cause") == "companion" for e in after), after
            assert svc.status()["active_mode"] is None  # whatever mode a disarmed PX4 reports

            # 5. shorter stalls: setpoints withheld under 0.5 s while a mission streams (PX4 still
            # flies our plan): the companion stops the mission and holds, in control
            await svc.commands.on_command(Command("takeoff", 1.0), time.monotonic())
            await until(lambda: svc.flight.state.value == "READY" and svc.flight.airborne, 30, "airborne again")
            spec = read("mission", b'{"id": "far", "origin": "home", "waypoints": [[-3, 0, -1.5]]}', svc.cfg,
                        st.home)
            await svc.navigator.on_mission(spec, time.monotonic())  # type: ignore[arg-type]
            await until(lambda: svc.flight.state.value == "STREAMING", 5, "streaming")
            mark = len(events.all)
            time.sleep(LIMIT + 0.2)
            await until(lambda: svc.flight.state.value == "HOLDING", 10, "holding after the short stall")
            assert svc.navigator.interrupted is not None and st.mode == "OFFBOARD"
            # ...withheld longer (PX4 may have given up on OFFBOARD): release control and ask
            # PX4 to hold (LOITER), before its own timeout would; `start` takes control again
            time.sleep(LIMIT + 0.7)
            await until(lambda: st.mode == "LOITER", 5, "LOITER")
            assert svc.flight.state.value == "FAILSAFE" and st.armed
            after = events.all[mark:]
            assert [e["setpoints_withheld"] for e in after if e["type"] == "stalled"] == [True, True]
            assert any(e["type"] == "handover" and e.get("cause") == "companion" for e in after), after
            assert not [e for e in after if e["type"] in ("link_lost", "pilot_takeover")], after

    try:
        asyncio.run(go())
    finally:
        mock.stop()
