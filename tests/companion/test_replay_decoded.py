"""Replay of how inbound messages were read: a real Recorder writes what `read` made of each
message (a typed message, or the refusal with its field and reason) with what it was given
(the bytes, home, the fleet frame), into a real MCAP file; replay reads every message again
with the recorded configuration and says whether each becomes the same (exit 0) or which one
differs (exit 1): a field bug's "wrong reason" becomes a regression test."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from recorder_support import config
from test_replay_transitions import rewrite

from companion import record_format, replay_cli
from companion.geodesy import Placement
from companion.recorder import Recorder
from companion.wire.errors import Oversized
from companion.wire.messages import read

TOPIC = "/inbound/decoded"
HOME = np.array([1.0, -2.0, 0.5])

MESSAGES: list[tuple[str, Any, dict[str, Any]]] = [
    ("mission", {"id": "m1", "waypoints": [[3, 0, -2], [3, 3, -2]]}, {}),
    ("mission", {"id": "m2", "waypoints": [[3, 0, -2], [3, "x", -2]]}, {}),  # refused: which field, why
    ("mission", {"id": "m3", "origin": "home", "waypoints": [[1, 1, -1.5]]}, {"home": HOME}),
    ("mission", {"id": "m4", "origin": "home", "waypoints": [[1, 1, -1.5]]}, {}),  # no home yet
    ("obstacles", {"add": [{"id": "b", "vertices": [[2, -1, -3], [2.5, -1, -3], [2, -0.5, -3], [2, -1, -2.5]]}]}, {}),
    ("change", {"mission": "m1", "move": [{"index": 1, "to": [4, 4, -2]}]}, {}),
    ("mission", {"id": "f1", "origin": "fleet", "waypoints": [[10, 0, -2]]},
     {"fleet": Placement(np.array([5.0, 0.0, 0.0]), source="offset_ned")}),
    ("command", {"command": "land"}, {}),
]


def record(tmp_path: Path, messages: list[tuple[str, Any, dict[str, Any]]] = MESSAGES) -> tuple[Path, list[Any]]:
    """Each message read as the service reads it and handed to the recorder as the service does;
    the file and what each became."""
    cfg = config(tmp_path)
    rec = Recorder(cfg)
    rec.open()
    made = []
    for i, (key, body, given) in enumerate(messages):
        payload: Any = json.dumps(body).encode() if body is not None else Oversized(10_000_000)
        context = {"home": given.get("home"), "home_pending": False, "fleet": given.get("fleet")}
        msg = read(key, payload, cfg, context["home"], fleet=context["fleet"])
        made.append(msg)
        rec.decoded(key, payload, context, msg, float(i))
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    return path, made


def decoded(path: Path) -> list[dict[str, Any]]:
    with open(path, "rb") as fh:
        return [json.loads(m.data) for _s, _c, m in make_reader(fh).iter_messages(topics=[TOPIC])]


def test_every_message_is_read_again_alike(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, made = record(tmp_path)
    recs = decoded(path)
    assert [r["seq"] for r in recs] == list(range(1, len(MESSAGES) + 1))
    # what each became, readable in the file: the refusals with their field and reason
    assert [r["ok"] for r in recs] == [not isinstance(m, Exception) for m in made]
    assert not recs[1]["ok"] and recs[1]["field"] == "waypoints[1][1]", recs[1]
    assert not recs[3]["ok"] and "home" in recs[3]["reason"], recs[3]
    assert recs[2]["ok"] and recs[6]["ok"] and recs[7]["type"] == "Command"
    assert replay_cli.main([str(path)]) == 0
    out = capsys.readouterr().out
    assert f"messages: {len(MESSAGES)} of {len(MESSAGES)} read again alike" in out, out


def test_a_message_read_differently_now_is_named(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """The file says the mission from home was refused for want of home (as if home had not
    been known): read again with the home it recorded, it is a mission: the difference names
    the message, what it was and what it is now."""
    path, _ = record(tmp_path)

    def as_refused(rec: dict[str, Any]) -> dict[str, Any]:
        if rec["seq"] == 3:
            rec = {**rec, "ok": False, "type": "MessageError", "field": "origin", "reason": "no home yet",
                   "fingerprint": record_format.decoded_fingerprint(ValueError("no home yet"))}
        return rec

    edited = rewrite(path, tmp_path / "edited.mcap", as_refused, topic=TOPIC)
    assert replay_cli.main([str(edited)]) == 1
    out = capsys.readouterr().out
    assert "messages: 7 of 8 read again alike; first difference: message 3 on mission: recorded MessageError " \
           "(origin: no home yet), read again MissionSpec" in out, out


def test_the_recorded_configuration_is_the_one_read_with(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A file whose configuration says [limits] max_waypoints 1: the two-waypoint missions now
    refused, where the recording service took them: named, exit 1."""
    path, _ = record(tmp_path)

    def fewer(name: str, md: dict[str, str]) -> dict[str, str]:
        if name == "companion":
            md = {**md, "config": md["config"].replace("max_waypoints = ", "max_waypoints = 1 #")}
        return md

    edited = rewrite(path, tmp_path / "edited.mcap", meta=fewer)
    assert replay_cli.main([str(edited)]) == 1
    out = capsys.readouterr().out
    assert "first difference: message 1 on mission: recorded MissionSpec, read again MessageError" in out, out


def test_an_oversized_message_is_read_again_as_one(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, made = record(tmp_path, [("mission", None, {})])
    assert isinstance(made[0], Exception)
    (rec,) = decoded(path)
    assert not rec["ok"] and "bytes" in rec["reason"], rec
    assert replay_cli.main([str(path)]) == 0
    assert "messages: 1 of 1 read again alike" in capsys.readouterr().out
