"""A recorded flight (mock PX4 + the companion, as deployed: `python -m companion run` with
`[recording] path` and `[live] foxglove`): the file opens with the `mcap` reader and has every
channel with its schema, holds every setpoint sent, replays bit-identically; the live view
serves the same channels while the vehicle flies."""

from __future__ import annotations

import asyncio
import json
import os
import re
import shutil
import socket
import struct
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import jsonschema
import pytest
import websockets
from e2e_rig import REPO, Rig, box, free_port
from mcap.reader import make_reader

pytestmark = pytest.mark.slow

SETPOINT = "/mavlink/out/SET_POSITION_TARGET_LOCAL_NED"
# what a flight with a plan, a replan and telemetry must have recorded
JSON_CHANNELS = ("/in/command", "/in/mission", "/in/change", "/out/status", "/out/events", "/out/telemetry",
                 "/out/trajectory", SETPOINT, "/mavlink/out/HEARTBEAT", "/mavlink/out/COMMAND_LONG",
                 "/mavlink/in/HEARTBEAT", "/mavlink/in/LOCAL_POSITION_NED", "/mavlink/in/ATTITUDE",
                 "/mavlink/in/COMMAND_ACK", "/planner/plan", "/viz/bounds", "/recorder/stats", "/supervisor/transition",
                 "/inbound/decoded", "/autopilot/step", "/tracking/step", "/control/swap", "/navigator/split",
                 "/commands/step", "/stalls/step", "/navigator/choice")
FOXGLOVE_CHANNELS = {"/viz/vehicle": "foxglove.PoseInFrame", "/viz/tf": "foxglove.FrameTransform",
                     "/viz/planned_path": "foxglove.PosesInFrame", "/viz/flown_path": "foxglove.PosesInFrame",
                     "/viz/obstacles": "foxglove.SceneUpdate", "/viz/corridors": "foxglove.SceneUpdate"}


class RecordingRig(Rig):
    def __init__(self, tmp: Path) -> None:
        # the recorder is tested here, not the lag compensation: the response the other PX4
        # flight tests fly against (PX4 SIH's ~0.3 s lag has tests of its own: test_lag_settles)
        super().__init__("px4", tmp, ("--response", "calibrated"))
        self.live_port = free_port()
        self.recordings = tmp / "recordings"

    def config_text(self) -> str:
        # a loaded test machine plans the takeoff climb and the mission late: a longer split
        # (the recorder is what is tested here, not the planner's latency)
        text = super().config_text().replace("[planner]\n", "[planner]\nsplit_ahead = 0.5\n", 1)
        return text + f"""
[recording]
path = "{self.recordings}"

[live]
foxglove = "127.0.0.1:{self.live_port}"
"""

    def stop_companion(self) -> int:
        """SIGTERM, as systemd stops it: the hand-over, then the recorder closes its file."""
        companion = self.procs[1]
        companion.terminate()
        return companion.wait(30)


class LiveClient(threading.Thread):
    """A Foxglove WebSocket client, in a thread, for the length of the flight."""

    def __init__(self, port: int, topics: tuple[str, ...]) -> None:
        super().__init__(daemon=True)
        self.port = port
        self.topics = topics
        self.info: dict[str, Any] = {}
        self.channels: dict[str, dict[str, Any]] = {}
        self.received: dict[str, list[bytes]] = {t: [] for t in topics}
        self.error: BaseException | None = None
        self.done = threading.Event()

    def run(self) -> None:
        try:
            asyncio.run(self._run())
        except BaseException as exc:
            self.error = exc

    async def _run(self) -> None:
        offered = ["foxglove.websocket.v1", "foxglove.sdk.v1"]  # as the Foxglove app offers them
        async with websockets.connect(f"ws://127.0.0.1:{self.port}", subprotocols=offered,  # type: ignore[arg-type]
                                      max_size=None) as ws:
            subs: dict[int, str] = {}
            while not self.done.is_set():
                try:
                    msg = await asyncio.wait_for(ws.recv(), 0.5)
                except TimeoutError:
                    continue
                if isinstance(msg, str):
                    body = json.loads(msg)
                    if body["op"] == "serverInfo":
                        self.info = body
                    elif body["op"] == "advertise":
                        for c in body["channels"]:
                            self.channels[c["topic"]] = c
                            if c["topic"] in self.topics:
                                sid = len(subs) + 1
                                subs[sid] = c["topic"]
                                await ws.send(json.dumps({"op": "subscribe",
                                                          "subscriptions": [{"id": sid, "channelId": c["id"]}]}))
                elif msg[0] == 0x01:
                    sid, _t = struct.unpack_from("<IQ", msg, 1)
                    self.received[subs[sid]].append(msg[13:])


@pytest.fixture(scope="module")
def flight(tmp_path_factory: pytest.TempPathFactory) -> Any:
    tmp = tmp_path_factory.mktemp("recorded")
    rig = RecordingRig(tmp)
    rig.start()
    live = LiveClient(rig.live_port, (SETPOINT, "/viz/vehicle", "/out/status"))
    try:
        live.start()
        rig.ensure_airborne()
        mission = {"id": "recorded", "frame": "ned", "origin": "home",
                   "obstacles": [box([0.7, 0.7, -3.0], [1.3, 1.3, 0.0])],
                   "waypoints": [[2.0, 0.0, -1.2], [2.0, 2.0, -1.2], [0.0, 2.0, -1.5], [-1.0, 0.0, -1.2]]}
        for attempt in range(3):  # a loaded test machine may plan too late for the split: sent again
            since = rig.mark()
            rig.put("mission", mission)
            got = rig.wait_event(lambda e: e.get("key") == "mission" and e["type"] in ("accepted", "rejected"), 30,
                                 "mission accepted or rejected", since)
            if got["type"] == "accepted":
                break
            assert "after the split time" in got["message"] and attempt < 2, got
        time.sleep(0.8)
        rig.put("change", {"move_waypoint": {"index": 3, "position": [-1.0, 0.4, -1.2]}})
        rig.wait_event(lambda e: e["type"] == "mission_complete" and e.get("mission") == "recorded", 60,
                       "mission complete", since)
        time.sleep(0.5)
        live.done.set()
        live.join(5)
        code = rig.stop_companion()
    finally:
        live.done.set()
        rig.stop()
    (path,) = sorted(rig.recordings.glob("*.mcap"))
    keep = os.environ.get("RECORDING_KEEP")  # where to copy the flight (to refresh tests/data)
    if keep:
        shutil.copy(path, keep)
    return {"path": path, "live": live, "exit": code, "events": rig.events}


def messages(path: Path) -> tuple[dict[str, Any], list[tuple[Any, Any, Any]]]:
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        return {m.name: dict(m.metadata) for m in reader.iter_metadata()}, list(reader.iter_messages())


def test_the_recording_opens_with_the_mcap_reader_with_every_channel_and_its_schema(flight: Any) -> None:
    assert flight["exit"] == 0  # handed over, file closed
    meta, msgs = messages(flight["path"])
    channels = {c.topic: (s, c) for s, c, _m in msgs}
    for topic in JSON_CHANNELS:
        schema, channel = channels[topic]
        assert (schema.encoding, channel.message_encoding) == ("jsonschema", "json"), topic
        assert json.loads(schema.data)["type"] == "object"
    for topic, name in FOXGLOVE_CHANNELS.items():
        schema, channel = channels[topic]
        assert (schema.name, schema.encoding, channel.message_encoding) == (name, "protobuf", "protobuf"), topic
    assert meta["companion"]["vehicle"] == "e2e" and json.loads(meta["recorder"]["dropped_total"]) == 0
    # every message of the flight validates against its channel's schema
    for schema, channel, message in msgs:
        if channel.message_encoding == "json":
            jsonschema.validate(json.loads(message.data), json.loads(schema.data))


def test_the_file_holds_every_setpoint_sent_at_50_hz(flight: Any) -> None:
    _meta, msgs = messages(flight["path"])
    sp = sorted(json.loads(m.data)["t"] for _s, c, m in msgs if c.topic == SETPOINT)
    statuses = [(m.log_time, json.loads(m.data)) for _s, c, m in msgs if c.topic == "/out/status"]
    # the companion's own count, from its last status while streaming, against the file's up to then
    log_time, last = max((x for x in statuses if x[1]["streaming"]), key=lambda x: x[0])
    times = sorted(m.log_time for _s, c, m in msgs if c.topic == SETPOINT)
    in_file = sum(1 for t in times if t <= log_time)
    assert abs(in_file - last["setpoints_sent"]) <= 2  # the thread may send between status() and its publication
    # one stream from arming to the hand-over: 50 Hz x its span, within 2 %
    span = sp[-1] - sp[0]
    assert span > 10
    assert abs(len(sp) - 50.0 * span) <= 0.02 * 50.0 * span


def test_every_plan_transition_and_step_of_the_flight_replays_bit_identically(flight: Any) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    run = subprocess.run([sys.executable, "-m", "companion", "replay", str(flight["path"])], cwd=REPO, env=env,
                         capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stdout + run.stderr
    lines = [ln for ln in run.stdout.splitlines() if ln.startswith("plan ") and not ln.startswith("plan choices")]
    assert len(lines) >= 3 and all(": identical" in ln for ln in lines)  # climb, mission, replan
    assert any("replan" in ln for ln in lines)
    _meta, msgs = messages(flight["path"])
    n = sum(1 for _s, c, _m in msgs if c.topic == "/supervisor/transition")
    assert n > 10 and f"transitions: {n} of {n} reproduced" in run.stdout.splitlines()
    # every call of the autopilot watch's rules reproduced, its events the transitions recorded
    steps = sum(1 for _s, c, _m in msgs if c.topic == "/autopilot/step")
    assert steps > 10 and any(ln.startswith(f"autopilot steps: {steps} of {steps} reproduced (")
                              and ln.endswith(" events, each a recorded transition)") for ln in run.stdout.splitlines())
    # every call of the tracking error's rules that changed or said something reproduced (a
    # record for each position sample of the flight's plans of ours; no brake in this flight)
    tracked = sum(1 for _s, c, _m in msgs if c.topic == "/tracking/step")
    assert tracked > 10 and f"tracking steps: {tracked} of {tracked} reproduced (0 brakes)" in run.stdout.splitlines()
    # every swap decision decided alike again (the climb, the mission and the replan swapped in)
    swapped = sum(1 for _s, c, _m in msgs if c.topic == "/control/swap")
    assert swapped >= 3 and any(ln.startswith(f"swaps: {swapped} of {swapped} decided alike (")
                                for ln in run.stdout.splitlines())
    # every step of the split-and-swap loop reproduced (the mission and the replan at least swapped in)
    split = sum(1 for _s, c, _m in msgs if c.topic == "/navigator/split")
    assert split >= 4 and any(ln.startswith(f"splits: {split} of {split} reproduced (") for ln in run.stdout.splitlines())
    # every question to the plan budget answered alike (the climb, the mission, the replan each
    # asked how far ahead to split; their planning times measured)
    budget = sum(1 for _s, c, _m in msgs if c.topic == "/navigator/budget")
    assert budget >= 6 and any(ln.startswith(f"budget: {budget} of {budget} reproduced (") for ln in run.stdout.splitlines())
    # every step of the operator commands' sequences reproduced (the takeoff sent over Zenoh: its
    # arm, the OFFBOARD it needs, the climb, and how the command ended), none failed, and each
    # transition a step made is the transition record it names
    commanded = sum(1 for _s, c, _m in msgs if c.topic == "/commands/step")
    said = next(ln for ln in run.stdout.splitlines() if ln.startswith("commands: "))
    made = re.search(r"; (\d+) of (\d+) transitions found as made\)$", said)
    assert commanded >= 10 and said.startswith(f"commands: {commanded} of {commanded} reproduced ("), said
    assert " 0 failed; " in said and made is not None and made[1] == made[2] != "0", said
    # the stall watch's start and the flight states it saw, replayed alike (no stall here)
    watched = sum(1 for _s, c, _m in msgs if c.topic == "/stalls/step")
    assert watched >= 3 and f"stalls: {watched} of {watched} reproduced (0 stalls: 0 held, 0 released control, 0 not " \
        "in control)" in run.stdout.splitlines(), run.stdout
    # which plan the mission's start and the change's replan asked for, replayed alike, each call
    # chosen found among the plans recorded
    choices = [json.loads(m.data) for _s, c, m in msgs if c.topic == "/navigator/choice"]
    runs = {r["rules"]["type"] for r in choices}
    chosen = sum(1 for r in choices if r["action"]["type"] == "Plan"
                 and r["action"]["fields"]["call"].startswith("companion.mission."))  # a stop records no plan
    said = next(ln for ln in run.stdout.splitlines() if ln.startswith("plan choices: "))
    assert {"StartRules", "ReplanRules"} <= runs, runs
    assert said.startswith(f"plan choices: {len(choices)} of {len(choices)} reproduced (") and \
        f"; {chosen} planner calls found as chosen; " in said, said
    # every inbound message the flight took in was read, and reads again the same (none was
    # dropped or refused on arrival in this flight)
    inbound = sum(1 for _s, c, _m in msgs if c.topic.startswith("/in/"))
    read_back = sum(1 for _s, c, _m in msgs if c.topic == "/inbound/decoded")
    assert inbound >= 3 and read_back == inbound, (inbound, read_back)
    assert f"messages: {inbound} of {inbound} read again alike" in run.stdout.splitlines(), run.stdout


def test_the_summary_tells_the_flight(flight: Any) -> None:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    run = subprocess.run([sys.executable, "-m", "companion", "recording", "summary", "--json", str(flight["path"])],
                         cwd=REPO, env=env, capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    s = json.loads(run.stdout)
    assert abs(s["setpoints"]["rate_hz"] - 50.0) < 1.0
    assert s["events_by_type"]["mission_complete"] == 1
    assert s["tracking_error_m"]["max"] < 1.0
    assert any(p["function"].startswith("companion.mission.start_mission") for p in s["plans"])


def test_the_live_view_served_the_flight_as_it_flew(flight: Any) -> None:
    live = flight["live"]
    assert live.error is None, live.error
    assert live.info["op"] == "serverInfo"
    assert live.channels["/viz/vehicle"]["schemaName"] == "foxglove.PoseInFrame"
    assert live.channels["/viz/vehicle"]["encoding"] == "protobuf"
    assert live.channels[SETPOINT]["schemaEncoding"] == "jsonschema"
    assert len(live.received[SETPOINT]) > 100  # seconds of the 50 Hz stream
    assert all(json.loads(b)["mavpackettype"] == "SET_POSITION_TARGET_LOCAL_NED" for b in live.received[SETPOINT])
    assert len(live.received["/viz/vehicle"]) > 50
    assert "STREAMING" in {json.loads(b)["state"] for b in live.received["/out/status"]}


def test_nothing_left_listening(flight: Any) -> None:
    """The companion stopped: nothing serves the live port any more."""
    with socket.socket() as s, pytest.raises(ConnectionRefusedError):
        s.connect(("127.0.0.1", flight["live"].port))
