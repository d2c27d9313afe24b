"""Replay: a recorded plan runs again bit-identically; a changed input is found and named; a
recording cannot make replay call anything but a planner function."""

from __future__ import annotations

import base64
import json
import os
import pickle
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from recorder_support import config, plan_call

from companion import record_format, replay, replay_cli
from companion.recorder import Recorder

DATA = Path(__file__).resolve().parents[1] / "data"


def record(tmp_path: Path, calls: list[tuple[Any, tuple[Any, ...], Any]]) -> Path:
    rec = Recorder(config(tmp_path))
    rec.open()
    for fn, args, out in calls:
        rec.plan(fn, args, out, 1.0, 1.2, "process")
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    return path


def plan_records(path: Path) -> list[dict[str, Any]]:
    with open(path, "rb") as fh:
        return [json.loads(m.data) for _s, _c, m in make_reader(fh).iter_messages(topics=["/planner/plan"])]


def test_a_recorded_plan_replays_bit_identically(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = config(tmp_path)
    path = record(tmp_path, [plan_call(cfg), plan_call(cfg, waypoints=[[0.0, 0.0, -1.0], [3.0, 1.0, -2.0]])])
    assert replay_cli.main([str(path)]) == 0
    out = capsys.readouterr().out
    assert out.count(": identical") == 2 and "plans: 2 of 2 reproduced bit-identically" in out
    assert "transitions: none recorded" in out  # no supervisor here: judged by the plans


def test_a_changed_input_is_found_and_where_the_result_differs_is_said(tmp_path: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    cfg = config(tmp_path)
    fn, args, out = plan_call(cfg)
    path = record(tmp_path, [(fn, args, out)])
    (rec,) = plan_records(path)
    jet = np.array(args[1])
    jet[0, 0] += 1e-9  # one bit of the start, as a field bug would differ
    rec["call"] = base64.b64encode(pickle.dumps((fn, (args[0], jet, *args[2:])))).decode()
    r = replay.replay_one(rec)
    assert not r.identical
    assert r.difference.startswith("result.route.") and "recorded" in r.difference and "replayed" in r.difference


def test_the_fingerprint_ignores_timings_and_sees_every_bit() -> None:
    cfg = config()
    _fn, _args, out = plan_call(cfg)
    assert out.route is not None
    again = pickle.loads(pickle.dumps(out))
    again.stats["took"] = 123.0  # timings differ from run to run
    assert record_format.fingerprint(again) == record_format.fingerprint(out)
    cp = out.route.trajectory.control_points.copy()
    cp.flat[17] = np.nextafter(cp.flat[17], np.inf)
    changed = pickle.loads(pickle.dumps(out))
    object.__setattr__(changed.route.trajectory, "control_points", cp)
    assert record_format.fingerprint(changed) != record_format.fingerprint(out)
    assert "control_points" in record_format.first_difference(out, changed)


class _Evil:
    def __reduce__(self) -> Any:
        return (os.system, ("echo pwned",))


def test_a_recording_cannot_name_any_other_function() -> None:
    bad = base64.b64encode(pickle.dumps((_Evil(), ()))).decode()
    with pytest.raises(pickle.UnpicklingError, match="does not load"):
        replay.loads(bad)
    evil_fn = base64.b64encode(pickle.dumps((eval, ("1",)))).decode()
    with pytest.raises(pickle.UnpicklingError, match=r"builtins.eval"):
        replay.loads(evil_fn)


def test_the_recorded_flight_in_tests_data_replays_bit_identically(capsys: pytest.CaptureFixture[str]) -> None:
    """A flight recorded by the service (mock PX4 + companion, tests/e2e/test_recording.py's
    flight), its planner calls kept (tests/data/README.md): the regression test a field
    recording becomes."""
    path = DATA / "flight-plans.mcap"
    assert replay_cli.main([str(path)]) == 0
    out = capsys.readouterr().out
    n = out.count(": identical")
    assert n >= 3 and f"plans: {n} of {n} reproduced bit-identically" in out
    # recorded before /supervisor/transition existed (and extracted to its plans): plans only
    assert "transitions: none recorded" in out.splitlines()


def test_the_recorded_flight_decisions_in_tests_data_replay_alike(capsys: pytest.CaptureFixture[str]) -> None:
    """A flight recorded by the service as deployed (tests/e2e/test_recording.py's: `python -m
    companion run` against mock PX4, a mission, a change, SIGTERM), its decision channels, inbound
    reads and plans kept (tests/data/README.md): every decision the service made in it, and every
    plan, made again alike. A change of any rule's behaviour, of the inbound reader or of the
    planner's numbers fails here until the flight is recorded again (which is the point: say why
    in the commit)."""
    import re

    assert replay_cli.main([str(DATA / "flight-decisions.mcap")]) == 0
    out = capsys.readouterr().out.splitlines()
    said = {ln.split(":")[0]: ln for ln in out if not re.match(r"plan +\d+ ", ln)}
    for loop in ("transitions", "autopilot steps", "heartbeats", "tracking steps", "swaps", "splits", "budget",
                 "commands", "stalls", "holds", "plan choices", "messages", "plans"):
        m = re.match(rf"{loop}: (\d+) of (\d+) ", said[loop])
        assert m is not None and m[1] == m[2] != "0", said[loop]
    assert "1 start, 1 stop; 3 planner calls found as chosen" in said["plan choices"]


def test_replay_gives_the_compiled_switch_back_as_it_found_it(tmp_path: Path) -> None:
    """A replay runs each call with the recording's choice of compiled pass; the switch is
    process-wide, so after the replay a caller's own plans run as they did before it (this leaked
    once, and the planner tests that ran after a replay in the same process planned uncompiled)."""
    from planner_core.window import kernel_unavailable, use_compiled_kernel

    cfg = config(tmp_path)
    path = record(tmp_path, [plan_call(cfg)])
    (rec,) = plan_records(path)
    for before, recorded in ((True, False), (False, True), (True, True)):
        use_compiled_kernel(before, "the caller's own reason")
        try:
            seen_before = kernel_unavailable()
            replay.replay_one({**rec, "compiled": recorded})
            assert kernel_unavailable() == seen_before
        finally:
            use_compiled_kernel(True)
