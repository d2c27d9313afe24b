"""Issue 23.4: the companion's decisions replayed. A flight (takeoff, a short mission, land) of
the in-process service against the in-process mock PX4, recording on; the file replays with
every supervisor transition, every autopilot step and every plan reproduced, and the
transitions in it are every `Supervisor.handle` call the service made: the ones that announced
a state change are the `state` events it published, one for one and in order; every event the
autopilot watch made is one of them, and each step made from a message came from a MAVLink
message the file holds."""

from __future__ import annotations

import asyncio
import collections
import itertools
import json
import time
from pathlib import Path
from typing import Any

import pytest
from companionkit import Events, service_for, serving, until
from mcap.reader import make_reader

from companion import replay_cli
from companion.flight import FlightState, State
from companion.report import clip
from companion.supervisor import Event
from companion.wire.messages import Command, read
from sitl_mock import MockAutopilot, MockConfig

pytestmark = pytest.mark.slow

def popup(at: list[float]) -> bytes:
    """A small box across the mission's last leg, halfway along it (NED)."""
    x, y, z = at
    eye = [[1.0, 0, 0], [0, 1.0, 0], [0, 0, 1.0], [-1.0, 0, 0], [0, -1.0, 0], [0, 0, -1.0]]
    lo, hi = [x + 0.6, y + 1.35, z - 0.8], [x + 0.9, y + 1.65, z + 0.4]
    return json.dumps({"add": [{"id": "popup", "A": eye, "b": [*hi, *(-v for v in lo)]}]}).encode()


def mission(at: Any) -> bytes:
    """A short square-ish leg from where the vehicle hovers (local NED: no wait for home)."""
    x, y, z = (float(v) for v in at)
    return json.dumps({"id": "replayed", "waypoints": [[x + 1.5, y, z], [x + 1.5, y + 1.5, z],
                                                       [x, y + 1.5, z - 0.3]]}).encode()


async def _fly(mock: MockAutopilot,
               recordings: Path) -> tuple[list[dict[str, Any]], int, FlightState, int, int, list[str], list[Any]]:
    svc = service_for(mock, recording={"path": str(recordings)}, safety={"takeoff_altitude": 1.5})
    events = Events(svc)
    calls = [0]
    handle = svc.flight.handle

    def counted(event: Event) -> Any:  # every call, counted apart from what the recorder saw
        calls[0] += 1
        return handle(event)

    svc.flight.handle = counted  # type: ignore[method-assign]
    steps = [0]
    step = svc.watch._step

    def stepped(*call: Any) -> Any:  # every call of the watch's rules, counted apart
        steps[0] += 1
        return step(*call)

    svc.watch._step = stepped  # type: ignore[method-assign,assignment]
    tracked = [0]
    record = svc.tap.tracking_step

    def tracking(*call: Any) -> None:  # every call of the tracking rules shown to the recorder, counted apart
        tracked[0] += 1
        record(*call)

    svc.tracking.connect(observe=tracking)
    decided: list[str] = []  # every swap the control decided: its refusal ("" swapped in)
    observe = svc.control.observe_swap

    def swap_seen(*call: Any) -> None:
        decided.append(call[-1])
        observe(*call)

    svc.control.observe_swap = swap_seen
    split: list[Any] = []  # every call of the split-and-swap loop's rules: its action
    record_split = svc.navigator.split.observe

    def split_seen(*call: Any) -> None:
        split.append(call[-1])
        record_split(*call)

    svc.navigator.split.observe = split_seen
    asked: list[Any] = []  # every question to the plan budget: (ask, answer)
    record_budget = svc.navigator.budget.observe

    def budget_seen(*call: Any) -> None:
        asked.append((call[1], call[3]))
        record_budget(*call)

    svc.navigator.budget.observe = budget_seen
    raced: list[Any] = []  # every call of the pop-ups' rules: its action
    record_race = svc.navigator.brakes.observe

    def race_seen(*call: Any) -> None:
        raced.append(call[-1])
        record_race(*call)

    svc.navigator.brakes.observe = race_seen
    commanded: list[tuple[str, Any]] = []  # every call of the command sequences' rules: its sequence and action
    record_command = svc.commands.observe

    def command_seen(*call: Any) -> None:
        commanded.append((call[2].sequence, call[-1]))
        record_command(*call)

    svc.commands.observe = command_seen
    async with serving(svc):
        await until(lambda: svc.link.state.position_problem() is None, 30, "a position estimate")
        await svc.commands.takeoff(1.5)
        assert svc.flight.airborne
        def answer(since: int) -> dict[str, Any] | None:
            return next((e for e in events.all[since:] if e["type"] in ("accepted", "rejected")
                         and e.get("key") == "mission"), None)

        for attempt in range(3):  # a loaded test machine may plan too late for the split: sent again
            seen = len(events.all)
            start = [float(v) for v in svc.link.state.position]
            svc.inbound.dispatch("mission", b"", time.monotonic(), read("mission", mission(start), svc.cfg))
            await until(lambda: answer(seen) is not None, 60, "the mission answered")  # noqa: B023 - awaited here
            got = answer(seen)
            assert got is not None
            if got["type"] == "accepted":
                break
            assert "after the split time" in got["message"] and attempt < 2, got
        # a pop-up across the last leg while the first is flown, raced against its braking
        # deadline: its inflated box (PX4's tracking allowance) covers the mission's waypoint 1, so
        # the replan finds it blocked and the vehicle brakes (or, on a loaded machine, its stop
        # by the deadline comes first); the mission's first leg is all the flight needs
        await asyncio.sleep(0.3)
        svc.inbound.dispatch("obstacles", b"", time.monotonic(), read("obstacles", popup(start), svc.cfg))
        await until(lambda: bool(events.of("mission_complete") or events.of("braking")), 90, "the mission flown")
        if events.of("braking"):
            await until(lambda: svc.flight.state is State.HOLDING, 30, "the stop flown")
        await svc.commands.on_command(Command("land"), time.monotonic())
        await until(lambda: any(e.get("command") == "land" and e["type"] in ("completed", "refused")
                                for e in events.all), 60, "land to complete")
        await until(lambda: svc.flight.state is State.IDLE, 30, "the autopilot's disarm after landing")
    return events.all, calls[0], svc.flight.value, steps[0], tracked[0], decided, split, asked, raced, commanded


def test_a_recorded_flight_replays_every_transition_and_plan(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    mock = MockAutopilot(MockConfig(autopilot="px4", endpoints=["udpin:127.0.0.1:0"],
                                    log_path=str(tmp_path / "flight.jsonl"), log_rate_hz=20)).start()
    try:
        published, handled, final, stepped, tracked, decided, split, asked, raced, commanded = asyncio.run(
            _fly(mock, tmp_path / "recordings"))
    finally:
        mock.stop()
    (path,) = sorted((tmp_path / "recordings").glob("*.mcap"))
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        dropped = json.loads({m.name: dict(m.metadata) for m in reader.iter_metadata()}["recorder"]["dropped"])
        recs = [json.loads(m.data) for _s, _c, m in reader.iter_messages(topics=["/supervisor/transition"])]
        steps = [json.loads(m.data) for _s, _c, m in reader.iter_messages(topics=["/autopilot/step"])]
        swaps = [json.loads(m.data) for _s, _c, m in reader.iter_messages(topics=["/control/swap"])]
        tracking = [json.loads(m.data) for _s, _c, m in reader.iter_messages(topics=["/tracking/step"])]
        splits = [json.loads(m.data) for _s, _c, m in reader.iter_messages(topics=["/navigator/split"])]
        budget = [json.loads(m.data) for _s, _c, m in reader.iter_messages(topics=["/navigator/budget"])]
        races = [json.loads(m.data) for _s, _c, m in reader.iter_messages(topics=["/brakes/race"])]
        commands = [json.loads(m.data) for _s, _c, m in reader.iter_messages(topics=["/commands/step"])]
        stalls = [json.loads(m.data) for _s, _c, m in reader.iter_messages(topics=["/stalls/step"])]
        choices = [json.loads(m.data) for _s, _c, m in reader.iter_messages(topics=["/navigator/choice"])]
        heard = collections.Counter(c.topic for _s, c, _m in reader.iter_messages(topics=[
            "/mavlink/in/HEARTBEAT", "/mavlink/in/LOCAL_POSITION_NED", "/mavlink/in/EXTENDED_SYS_STATE"]))
    assert dropped == {}

    # every handle call is in the file, numbered without a gap, and the chain ends where the
    # service's supervisor ended
    assert [r["seq"] for r in recs] == list(range(1, handled + 1))
    assert recs[0]["before"] == {"state": "IDLE", "airborne": False, "seen_link": False, "link_lost": False,
                                 "exit_requested": False, "disarm_requested": False, "starting": False,
                                 "ground_z": None}
    assert recs[-1]["after"]["state"] == final.state.value == "IDLE"

    # the transitions that announced are the `state` events published, one for one, in order
    # (Announce is the only path to a `state` event); the others changed no state
    announced = [(a["fields"]["src"], a["fields"]["dst"], clip(a["fields"]["reason"]))
                 for r in recs for a in r["actions"] if a["type"] == "Announce"]
    states = [(e["from"], e["to"], e["message"]) for e in published if e["type"] == "state"]
    assert announced == states
    quiet = [r for r in recs if not any(a["type"] == "Announce" for a in r["actions"])]
    assert len(recs) == len(states) + len(quiet)
    assert all(r["before"]["state"] == r["after"]["state"] for r in quiet)
    # (a stop for the pop-up by its deadline, on a loaded machine, brakes before the hold)
    braked = ["BRAKING"] if any(type(a).__name__ in ("Brake", "Braked") for a in raced) else []
    assert [s[1] for s in states] == ["ARMING", "READY", "TAKEOFF", "READY", "STREAMING", *braked, "HOLDING",
                                      "LANDING", "IDLE"]

    # every call of the autopilot watch's rules is in the file, numbered without a gap; each
    # reading of a message is one the link received and recorded (a step per message: no more
    # than the file's messages of that kind), and the supervisor events the steps made are
    # every transition of the kinds only the watch makes
    assert [r["seq"] for r in steps] == list(range(1, stepped + 1))
    kinds = collections.Counter(r["reading"]["type"] for r in steps)
    assert 0 < kinds["HeartbeatSeen"] <= heard["/mavlink/in/HEARTBEAT"]
    assert 0 < kinds["PositionSeen"] <= heard["/mavlink/in/LOCAL_POSITION_NED"]
    assert kinds["LandedStateSeen"] <= heard["/mavlink/in/EXTENDED_SYS_STATE"] and kinds["LinkCheck"] > 0
    made = [o["type"] for r in steps for o in r["outputs"] if o["type"] not in ("LinkFound", "LinkRestored", "Relay")]
    watch_kinds = {"Heartbeat", "Disarmed", "ModeReport", "GroundLearnt", "HeightReport", "LandedStateReport",
                   "LinkLost"}
    assert made == [r["event"]["type"] for r in recs if r["event"]["type"] in watch_kinds]
    assert "LinkFound" in [o["type"] for r in steps for o in r["outputs"]]

    # every call of the tracking error's rules that changed or said something is in the file,
    # numbered without a gap: one a position sample while a plan of ours is flown (the samples
    # of the mission and the hovers around it), and no brake in this flight
    assert [r["seq"] for r in tracking] == list(range(1, tracked + 1))
    assert 0 < tracked <= heard["/mavlink/in/LOCAL_POSITION_NED"]
    assert not any(o["type"] == "Brake" for r in tracking for o in r["outputs"])

    # replay: every transition, every step and every plan (the climb and the mission at least) reproduced
    assert replay_cli.main([str(path)]) == 0
    out = capsys.readouterr().out
    print(out)  # what the replay said (docs/recording.md quotes it)
    assert f"transitions: {handled} of {handled} reproduced" in out.splitlines()
    assert (f"autopilot steps: {stepped} of {stepped} reproduced ({len(made)} events, each a recorded "
            "transition)") in out.splitlines()
    # every swap the control decided is in the file, in order, and decided alike again: at least
    # the climb's and the mission's plans swapped in
    assert [r["refusal"] for r in swaps] == decided and [r["seq"] for r in swaps] == list(range(1, len(decided) + 1))
    n_in = decided.count("")
    assert n_in >= 2
    assert f"swaps: {len(decided)} of {len(decided)} decided alike ({n_in} swapped in, {len(decided) - n_in} refused)" \
        in out.splitlines()
    # each heartbeat's mode and armed state read again from its fields as the mock sent them
    beats = kinds["HeartbeatSeen"]
    assert (f"heartbeats: {beats} of {beats} read again alike (mode and armed from each one's fields as "
            "received)") in out.splitlines()
    assert f"tracking steps: {tracked} of {tracked} reproduced (0 brakes)" in out.splitlines()
    # every step of the split-and-swap loop (the mission's start, its anytime improvement, any
    # plan again) is in the file, in order, and reproduced; a swap it saw is that swap's record
    assert [r["action"]["type"] for r in splits] == [type(a).__name__ for a in split]
    assert [r["seq"] for r in splits] == list(range(1, len(split) + 1))
    ends = [type(a).__name__ for a in split if type(a).__name__ in ("Done", "GiveUp", "Refused")]
    assert "Done" in ends
    assert (f"splits: {len(split)} of {len(split)} reproduced ({ends.count('Done')} swapped in, "
            f"{len(ends) - ends.count('Done')} given up)") in out.splitlines()
    # every question to the plan budget (the warm-up's planning time measured first, how far
    # ahead the climb's and the mission's plans split, each plan's time measured) is in the file,
    # in order, and answered alike again from the times measured before it
    assert [(r["ask"]["type"], r["answer"]) for r in budget] == [(type(a).__name__, x) for a, x in asked]
    assert [r["seq"] for r in budget] == list(range(1, len(asked) + 1))
    kinds_asked = [type(a).__name__ for a, _x in asked]
    assert kinds_asked[0] == "Measured" and "SplitAhead" in kinds_asked and kinds_asked.count("Measured") >= 3
    assert (f"budget: {len(asked)} of {len(asked)} reproduced ({len(asked) - kinds_asked.count('Measured')} "
            f"split or search asked, {kinds_asked.count('Measured')} planning times measured)") in out.splitlines()
    # every step of the pop-up and its race (its decision, the deadline, each turn, the end) is
    # in the file, in order, and reproduced; a stop by the deadline is its Braking transition
    assert [r["action"]["type"] for r in races] == [type(a).__name__ for a in raced]
    assert [r["seq"] for r in races] == list(range(1, len(raced) + 1))
    kinds = collections.Counter(type(a).__name__ for a in raced)
    assert kinds["Race"] == 1 and kinds["Forwarded"] >= 1 and kinds["Won"] + kinds["Brake"] + kinds["Braked"] == 1
    brakes = kinds["Brake"] + kinds["Braked"]
    tied = f", {brakes} followed by its Braking transition" if brakes else ""
    assert (f"races: {len(raced)} of {len(raced)} reproduced (1 pop-up, 1 raced, {brakes} "
            f"brake{'s' * (brakes != 1)}{tied})") in out.splitlines(), out
    # every step of the operator commands' sequences (takeoff: its arm, the OFFBOARD it needs,
    # the climb; land: the landing and its wait for the ground, and how it ended) is in the file,
    # in order, and reproduced; the transitions they made are the supervisor's of those kinds,
    # each the transition record the step named
    assert [(r["rules"]["sequence"], r["action"]["type"]) for r in commands] == \
        [(sequence, type(a).__name__) for sequence, a in commanded]
    assert [r["seq"] for r in commands] == list(range(1, len(commanded) + 1))
    assert {r["rules"]["sequence"] for r in commands} == {"takeoff", "arm", "follow", "climb", "land", "on_ground",
                                                          "outcome"}
    made_by_commands = [a.event if type(a).__name__ == "Transition" else "ControlTaken" for _s, a in commanded
                        if type(a).__name__ in ("Transition", "TakeControl")]
    command_kinds = {"TakingControl", "ControlTaken", "ArmRequested", "Armed", "TakeoffBegan", "TookOff",
                     "LandRequested"}
    assert made_by_commands == [r["event"]["type"] for r in recs if r["event"]["type"] in command_kinds]
    runs = [type(a).__name__ for _s, a in commanded if type(a).__name__ in ("Finish", "Fail")]
    assert runs and set(runs) == {"Finish"}
    n = len(commanded)
    assert (f"commands: {n} of {n} reproduced ({len(runs)} runs finished, 0 failed; {len(made_by_commands)} of "
            f"{len(made_by_commands)} transitions found as made)") in out.splitlines()
    # the stall watch: no stall in this flight; its start and every flight state it saw before
    # any stall (what a `stalled` event would name), in order, replayed alike
    assert stalls[0]["observation"] == {"type": "Settled", "fields": {"state": "IDLE"}}
    assert [r["seq"] for r in stalls] == list(range(1, len(stalls) + 1))
    seen = [r["after"]["was"] for r in stalls]
    # (the watch sees the state at its beats: a brief one, such as the hold between the mission and
    # the landing, can fall between two on a loaded runner; each it saw is one the supervisor made)
    made = {"IDLE"} | {r["after"]["state"] for r in recs}
    assert "STREAMING" in seen and set(seen) <= made and all(a != b for a, b in itertools.pairwise(seen)), seen
    assert f"stalls: {len(stalls)} of {len(stalls)} reproduced (0 stalls: 0 held, 0 released control, 0 not in " \
           "control)" in out.splitlines()
    # which plan the mission's start, the pop-up's replan and the stop asked for, replayed alike,
    # each planner call chosen found among the plans recorded (and those replay bit-identically)
    kinds = collections.Counter(r["rules"]["type"] for r in choices if r["step"] == 1)
    assert kinds["StartRules"] == 1 and kinds["StopRules"] >= 1, kinds
    calls = sum(1 for r in choices if r["action"]["type"] == "Plan"
                and r["action"]["fields"]["call"].startswith("companion.mission."))
    said = next(ln for ln in out.splitlines() if ln.startswith("plan choices: "))
    assert said.startswith(f"plan choices: {len(choices)} of {len(choices)} reproduced (") and \
        f"; {calls} planner calls found as chosen; " in said and calls >= 1, said
    plans = [ln for ln in out.splitlines() if ln.startswith("plan ") and not ln.startswith("plan choices")]
    assert len(plans) >= 2 and all(": identical" in ln for ln in plans)
    assert f"plans: {len(plans)} of {len(plans)} reproduced bit-identically" in out.splitlines()
