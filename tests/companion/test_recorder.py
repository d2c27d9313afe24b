"""The flight recorder: files the `mcap` reader opens, a schema on every channel, rotation,
and a bounded, never-blocking queue whose drops are counted and never hit setpoints."""

from __future__ import annotations

import json
import threading
import time
from pathlib import Path
from typing import Any

import jsonschema
import numpy as np
import pytest
from mcap.reader import make_reader
from recorder_support import Wire, config, plan_call

from companion.autopilot_rules import HeartbeatSeen, WatchRules, WatchState, watch_step
from companion.recorder import McapSink, Recorder
from companion.setpoints import Feed, SetpointSender, YawPolicy
from companion.supervisor import Heartbeat, Supervisor, TakingControl
from companion.wire.errors import Oversized
from companion.wire.messages import read
from planner_core import hold


def read_all(path: Path) -> tuple[dict[str, Any], list[tuple[Any, Any, Any]]]:
    with open(path, "rb") as fh:
        reader = make_reader(fh)
        meta = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        return meta, list(reader.iter_messages())


def only_file(directory: Path) -> Path:
    files = sorted(directory.glob("*.mcap"))
    assert len(files) == 1, files
    return files[0]


def record_a_little_of_everything(rec: Recorder) -> None:
    wire = Wire(rec.mavlink_sent)
    now = time.monotonic()
    rec.inbound("mission", b'{"id": "m"}', now)
    rec.inbound("command", b"\xff\xfe not utf-8", now)
    rec.inbound("obstacles", Oversized(5_000_000), now)
    for payload in (b'{"id": "m"}', Oversized(5_000_000)):  # refused: no waypoints; too large
        context = {"home": None, "home_pending": False, "fleet": None}
        rec.decoded("mission", payload, context, read("mission", payload, rec.cfg), now)
    rec.outbound("status", json.dumps({"state": "READY", "tracking_error": 0.1}).encode(), now)
    rec.outbound("events", json.dumps({"type": "started", "message": "hi"}).encode(), now)
    for k in range(10):
        wire.setpoint(k)
    wire.tx.command_long_send(1, 1, 176, 0, 1.0, 6.0, float("nan"), 0.0, 0.0, 0.0, 0.0)
    rec.mavlink_received(wire.received(wire.tx.attitude_encode(0, 0.1, -0.05, 0.5, 0.0, 0.0, 0.0)), now)
    for k in range(5):
        rec.mavlink_received(wire.received(wire.tx.local_position_ned_encode(k, 0.1 * k, 0.0, -1.0, 0, 0, 0)),
                             now + 0.3 * k)
    fn, args, out = plan_call(rec.cfg)
    rec.plan(fn, args, out, now, now + 0.05, "process")
    assert out.route is not None
    rec.flown(out.route.trajectory, now - 1.0, now + 0.06)
    sup = Supervisor()
    sup.connect(observe=rec.transition)
    sup.handle(Heartbeat())
    sup.handle(TakingControl("arm command"))
    ws, reading = WatchState(), HeartbeatSeen("px4", "POSCTL", True, False, 1, 1)
    rec.autopilot_step(ws, sup.value, reading, now, *watch_step(WatchRules(), ws, sup.value, reading, now))


def test_the_file_opens_with_the_mcap_reader_and_every_message_matches_its_schema(tmp_path: Path) -> None:
    rec = Recorder(config(tmp_path))
    rec.open()
    record_a_little_of_everything(rec)
    rec.close()
    meta, messages = read_all(only_file(tmp_path))
    channels = {c.topic: (s, c) for s, c, _ in messages}
    for topic in ("/in/mission", "/in/command", "/in/obstacles", "/out/status", "/out/events",
                  "/mavlink/out/SET_POSITION_TARGET_LOCAL_NED", "/mavlink/out/COMMAND_LONG",
                  "/mavlink/in/ATTITUDE", "/mavlink/in/LOCAL_POSITION_NED", "/planner/plan", "/viz/bounds",
                  "/recorder/stats", "/supervisor/transition", "/inbound/decoded", "/autopilot/step"):
        schema, channel = channels[topic]
        assert (schema.encoding, channel.message_encoding) == ("jsonschema", "json"), topic
    for topic, kind in (("/viz/vehicle", "foxglove.PoseInFrame"), ("/viz/tf", "foxglove.FrameTransform"),
                        ("/viz/planned_path", "foxglove.PosesInFrame"), ("/viz/flown_path", "foxglove.PosesInFrame"),
                        ("/viz/corridors", "foxglove.SceneUpdate"), ("/viz/obstacles", "foxglove.SceneUpdate")):
        schema, channel = channels[topic]
        assert (schema.name, schema.encoding, channel.message_encoding) == (kind, "protobuf", "protobuf"), topic
        assert len(schema.data) > 100  # the SDK's FileDescriptorSet, not a placeholder
    for schema, channel, message in messages:
        if channel.message_encoding == "json":
            jsonschema.validate(json.loads(message.data), json.loads(schema.data))
    by_topic: dict[str, list[Any]] = {}
    for _s, c, m in messages:
        by_topic.setdefault(c.topic, []).append(json.loads(m.data) if c.message_encoding == "json" else m)
    assert len(by_topic["/mavlink/out/SET_POSITION_TARGET_LOCAL_NED"]) == 10
    assert [r["x"] for r in by_topic["/mavlink/out/SET_POSITION_TARGET_LOCAL_NED"]] == pytest.approx(
        [0.01 * k for k in range(10)])
    assert by_topic["/mavlink/out/COMMAND_LONG"][0]["param3"] is None  # NaN: JSON has none
    assert by_topic["/in/mission"][0]["text"] == '{"id": "m"}'
    assert "base64" in by_topic["/in/command"][0] and by_topic["/in/obstacles"][0]["oversized"]
    plan = by_topic["/planner/plan"][0]
    assert plan["function"] == "companion.mission.start_mission" and plan["ok"] and plan["latency_ms"] == 50.0
    assert plan["trajectory"]["segments"] and plan["call"] and plan["result"]
    assert 0 < by_topic["/viz/bounds"][0]["velocity"] <= rec.cfg.planner.bounds.velocity
    assert [(t["seq"], t["event"]["type"], t["after"]["state"]) for t in by_topic["/supervisor/transition"]] == [
        (1, "Heartbeat", "IDLE"), (2, "TakingControl", "ARMING")]
    (step,) = by_topic["/autopilot/step"]
    assert (step["seq"], step["transition"], step["flight"]["state"]) == (1, 3, "ARMING")
    assert [o["type"] for o in step["outputs"]] == ["Heartbeat", "ModeReport"]
    assert "[recording]" in meta["companion"]["config"] and float(meta["companion"]["monotonic_to_unix"]) > 1e9
    assert json.loads(meta["recorder"]["dropped_total"]) == 0


def test_log_times_are_unix_time_and_keep_the_records_monotonic_times(tmp_path: Path) -> None:
    rec = Recorder(config(tmp_path))
    rec.open()
    t = time.monotonic()
    rec.outbound("status", b'{"a":1}', t)
    rec.close()
    meta, messages = read_all(only_file(tmp_path))
    (_s, _c, m), = [x for x in messages if x[1].topic == "/out/status"]
    offset = float(meta["companion"]["monotonic_to_unix"])
    assert m.log_time == int((t + offset) * 1e9)
    assert abs(m.log_time / 1e9 - time.time()) < 60


def test_a_full_queue_drops_and_counts_without_waiting(tmp_path: Path) -> None:
    """No writer thread runs: a blocking put would hang here."""
    rec = Recorder(config(tmp_path, queue=64))
    for k in range(1000):
        rec.inbound("obstacles", b"{}", float(k))
    wire = Wire(rec.mavlink_sent)
    for k in range(100):
        wire.setpoint(k)
    sup = Supervisor()
    sup.connect(observe=rec.transition)
    for _ in range(70):
        sup.handle(Heartbeat())
    # each kind on its own queue: the inbound flood took none of the others' room
    assert rec.dropped == {"inbound": 936, "mavlink_sent": 36, "transition": 6}
    assert rec.status_fields()["recording"]["dropped"] == 978


def test_a_burst_drops_other_records_never_setpoints_and_counts_every_drop(tmp_path: Path) -> None:
    """The setpoint thread sends at 50 Hz through pymavlink's send callback (as the service
    does) while another thread floods the recorder; every setpoint sent is in the file, every
    supervisor transition handled meanwhile too, and what is not in the file is exactly what
    was counted as dropped."""
    rec = Recorder(config(tmp_path, queue=256))
    rec.open()
    wire = Wire(rec.mavlink_sent)
    sent = [0]

    def send(sp: Any) -> None:
        sent[0] += 1
        wire.tx.set_position_target_local_ned_send(sent[0], 1, 1, 1, 2048, *sp.position, *sp.velocity,
                                                   *sp.acceleration, sp.yaw, 0.0)

    sender = SetpointSender(50.0, send, YawPolicy("hold", 0.0, 0.3), lambda _t: None, lambda _e: None)
    sender.feed = Feed(hold(np.array([0.0, 0.0, -1.0]), 0.0), time.monotonic())
    burst = 60_000
    stop = threading.Event()

    def flood() -> None:
        for k in range(burst):
            rec.inbound("obstacles", b'{"clear": true}', float(k))
        stop.set()

    sup = Supervisor()
    sup.connect(observe=rec.transition)
    sender.start()
    flooder = threading.Thread(target=flood)
    flooder.start()
    handled = 0
    while True:  # the loop's heartbeats, at a loop's pace, during the flood
        sup.handle(Heartbeat())
        handled += 1
        if stop.wait(0.005):
            break
    flooder.join()
    time.sleep(0.5)
    sender.stop()
    rec.close()
    meta, messages = read_all(only_file(tmp_path))
    setpoints = [json.loads(m.data) for _s, c, m in messages if c.topic == "/mavlink/out/SET_POSITION_TARGET_LOCAL_NED"]
    inbound = sum(1 for _s, c, _m in messages if c.topic == "/in/obstacles")
    assert sent[0] > 10
    assert [r["time_boot_ms"] for r in setpoints] == list(range(1, sent[0] + 1))  # every one, in order
    dropped = json.loads(meta["recorder"]["dropped"])
    assert dropped.get("mavlink_sent", 0) == 0 and dropped.get("transition", 0) == 0
    transitions = [json.loads(m.data)["seq"] for _s, c, m in messages if c.topic == "/supervisor/transition"]
    assert handled > 0 and sorted(transitions) == list(range(1, handled + 1))
    assert dropped["inbound"] > 0  # the burst did overflow the queue ...
    assert inbound + dropped["inbound"] == burst  # ... and every record is in the file or counted
    assert json.loads(meta["recorder"]["dropped_total"]) == dropped["inbound"]


def test_files_rotate_at_max_bytes_and_the_oldest_go_past_keep_bytes(tmp_path: Path) -> None:
    rng = np.random.default_rng(1)
    sink = McapSink(tmp_path, "v", max_bytes=40_000, keep_bytes=120_000, metadata={"vehicle": "v"})
    for k in range(4000):  # incompressible: ~1.2 MB in all
        sink.write("/out/status", json.dumps({"k": k, "noise": rng.bytes(200).hex()}).encode(), k * 1000)
    sink.close({"dropped": {}})
    assert sink.part >= 20
    kept = sorted(tmp_path.glob("*.mcap"))
    assert sink.files[0] not in kept and sink.path in kept  # the first went, the current stays
    older = [p for p in kept if p != sink.path]
    assert sum(p.stat().st_size for p in older) <= 120_000
    assert all(p.stat().st_size >= 40_000 for p in older)  # each closed past max_bytes
    ks = []
    for p in kept:  # every kept file is complete (summary and footer) and readable
        meta, messages = read_all(p)
        assert meta["companion"]["vehicle"] == "v"
        ks += [json.loads(m.data)["k"] for _s, _c, m in messages]
    assert ks == list(range(ks[0], 4000))  # contiguous up to the last record: nothing lost in a rotation


def test_off_by_default_and_the_service_pays_one_call() -> None:
    from companion.recorder import tap_for
    from companion.tap import Tap

    tap = tap_for(config())
    assert type(tap) is Tap and tap.status_fields() == {}
    assert isinstance(tap_for(config("/tmp/x")), Recorder)


def test_a_recording_that_cannot_be_written_is_said_and_the_service_goes_on(tmp_path: Path) -> None:
    blocker = tmp_path / "a-file"
    blocker.write_text("not a directory")
    rec = Recorder(config(blocker / "recordings"))
    rec.open()  # does not raise
    rec.outbound("status", b"{}", time.monotonic())
    rec.close()
    fields = rec.status_fields()["recording"]
    assert fields["file"] is None and "[recording] path" in fields["error"]


def test_a_sink_that_fails_mid_flight_is_given_up_once(tmp_path: Path) -> None:
    class Full:
        writes = 0

        def write(self, topic: str, data: bytes, log_time: int) -> None:
            Full.writes += 1
            raise OSError(28, "No space left on device")

        def close(self, stats: dict[str, Any]) -> None:
            pass

    rec = Recorder(config(tmp_path), sinks=[Full()])
    rec.open()
    for k in range(100):
        rec.outbound("status", b"{}", float(k))
    rec.close()
    assert Full.writes == 1 and "No space left" in str(rec.status_fields()["recording"]["error"])
    _meta, messages = read_all(only_file(tmp_path))  # the file sink went on
    assert sum(1 for _s, c, _m in messages if c.topic == "/out/status") == 100


def test_the_systemd_units_recording_directory_is_the_default_unless_the_file_says(tmp_path: Path,
                                                                                  monkeypatch: pytest.MonkeyPatch) -> None:
    from companion.cli_run import RECORDING_ENV, recording_default
    from companion.config import load_config

    monkeypatch.setenv(RECORDING_ENV, "/var/lib/bezier-companion/uav1")
    plain, off, own = tmp_path / "plain.toml", tmp_path / "off.toml", tmp_path / "own.toml"
    plain.write_text("[vehicle]\nid = 'uav1'\n")
    off.write_text("[recording]\npath = ''\n")
    own.write_text("[recording]\npath = '/data/rec'\n")
    assert recording_default(load_config(plain), str(plain)).recording.path == "/var/lib/bezier-companion/uav1"
    assert recording_default(load_config(off), str(off)).recording.path == ""
    assert recording_default(load_config(own), str(own)).recording.path == "/data/rec"
    monkeypatch.delenv(RECORDING_ENV)
    assert recording_default(load_config(plain), str(plain)).recording.path == ""


def test_the_systemd_unit_records_into_its_state_directory() -> None:
    from companion.cli_run import RECORDING_ENV

    unit = (Path(__file__).resolve().parents[2] / "systemd" / "bezier-companion@.service").read_text()
    lines = [ln.strip() for ln in unit.splitlines()]
    assert "StateDirectory=bezier-companion/%i" in lines
    assert f"Environment={RECORDING_ENV}=%S/bezier-companion/%i" in lines  # %S/<StateDirectory>


def test_a_file_cut_short_by_a_crash_keeps_its_complete_chunks(tmp_path: Path) -> None:
    """SIGKILL mid-flight: no summary; the summary tool still reads the chunks written."""
    from companion.recording import summarize

    rec = Recorder(config(tmp_path))
    rec.open()
    wire = Wire(rec.mavlink_sent)
    for k in range(3000):  # ~1 MB of records: several 128 kB chunks
        wire.setpoint(k)
        rec.outbound("status", json.dumps({"state": "STREAMING", "k": k, "pad": "x" * 200}).encode(), float(k))
    rec.close()
    path = only_file(tmp_path)
    data = path.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(data[: len(data) // 2])
    s = summarize(str(cut))
    n = s["channels"]["/mavlink/out/SET_POSITION_TARGET_LOCAL_NED"]["messages"]
    assert 0 < n < 3000
    full = summarize(str(path))
    assert full["channels"]["/mavlink/out/SET_POSITION_TARGET_LOCAL_NED"]["messages"] == 3000
