"""Replay of the swap's rule: a real `Control` wired to a real Recorder as the service wires it
decides swaps (a plan swapped in, one whose split had passed, one that is not the flown plan
before its split), recorded into a real MCAP file; replay decides each again alike (exit 0);
a changed decision, today's rule changed, a removed record, records the recorder dropped are
each named (exit 1); a swap record cannot make replay load anything but trajectories."""

from __future__ import annotations

import base64
import json
import os
import pickle
import time
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from mcap.reader import make_reader
from recorder_support import config, schema_checked
from test_replay_transitions import rewrite

from companion import replay_cli, replay_swaps
from companion.control import SWAP_DIFFERS, SWAP_LATE, Control
from companion.recorder import Recorder
from companion.setpoints import Feed, YawPolicy
from planner_core import hold, splice
from tests.companion.test_route import fly

TOPIC = "/control/swap"
HERE = np.array([0.0, 0.0, -1.5])


class Target:
    feed: Feed | None = None
    lead = 0.06


def decide(ctl: Control) -> list[str]:
    """Three swaps as the navigator asks for them: a mission planned from the hold, swapped in
    a little ahead; a plan whose split had passed; a hold elsewhere (not the flown plan)."""
    out = []
    t_split = ctl.now() + 0.3
    route = fly([[3.0, 0.0, -1.5], [3.0, 3.0, -1.5]], HERE.tolist(), t0=t_split)
    out.append(ctl.refusal if not ctl.swap(splice(ctl.active, route.trajectory), t_split, None, "mission m",  # type: ignore[arg-type]
                                           route) else "")
    now = ctl.now()
    out.append(ctl.refusal if not ctl.swap(hold(np.array(ctl.jet(now)[0]), now), now, None, "late") else "")
    now = ctl.now()
    out.append(ctl.refusal if not ctl.swap(hold(HERE + np.array([1.0, 0.0, 0.0]), now + 0.3), now + 0.3, None,
                                           "elsewhere") else "")
    return out


def recorded(tmp_path: Path, queue: int = 4096, early: int = 0) -> tuple[Path, Recorder, list[str]]:
    """`early`: as many decisions before the writer thread starts (they wait in the queue, or
    are dropped)."""
    rec = Recorder(config(tmp_path, queue=queue))
    ctl = Control(Target(), lambda sp: None, YawPolicy("fixed", 0.0, 0.5), 50.0)
    ctl.observe_swap = rec.swap
    ctl.take(HERE, 0.0, "test")
    time.sleep(0.02)
    for _ in range(early):
        ctl.swap(hold(HERE, ctl.now()), ctl.now() - 1.0, None, "early")
    rec.open()
    decided = decide(ctl)
    rec.close()
    (path,) = tmp_path.glob("*.mcap")
    return path, rec, decided


def swaps(path: Path) -> list[dict[str, Any]]:
    with open(path, "rb") as fh:
        return [json.loads(m.data) for _s, _c, m in make_reader(fh).iter_messages(topics=[TOPIC])]


def run(path: Path, capsys: pytest.CaptureFixture[str]) -> tuple[int, str]:
    code = replay_cli.main([str(path)])
    return code, capsys.readouterr().out


def line(out: str) -> str:
    return next(ln for ln in out.splitlines() if ln.startswith("swaps:"))


def test_every_swap_is_recorded_and_decided_alike_again(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, rec, decided = recorded(tmp_path)
    assert decided == ["", SWAP_LATE, SWAP_DIFFERS]
    recs = swaps(path)
    assert rec.dropped == {} and [r["seq"] for r in recs] == [1, 2, 3]
    assert [r["refusal"] for r in recs] == decided and [r["what"] for r in recs] == ["mission m", "late", "elsewhere"]
    assert all(r["lead"] == Target.lead and r["rate_hz"] == 50.0 for r in recs)
    assert schema_checked(path, TOPIC, "bezier.ControlSwap") == recs
    code, out = run(path, capsys)
    assert code == 0, out
    assert "swaps: 3 of 3 decided alike (1 swapped in, 2 refused)" in out.splitlines()


def test_a_changed_decision_is_found_with_its_seq(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _rec, _d = recorded(tmp_path / "rec")
    edited = rewrite(path, tmp_path / "changed.mcap", lambda r: {**r, "refusal": ""} if r["seq"] == 2 else r,
                     topic=TOPIC)
    code, out = run(edited, capsys)
    assert code == 1, out
    said = line(out)
    assert said.startswith("swaps: 2 of 3 decided alike; first difference: swap 2 (late) at "), said
    assert f"recorded swapped in, decided again {SWAP_LATE!r}" in said


def test_todays_rule_is_what_decides_again(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """A rule that changed since the flight (here: a split must be a whole second ahead) makes
    the recorded swap-in differ."""
    path, _rec, _d = recorded(tmp_path / "rec")
    from companion import control

    real = control.swap_refusal

    def stricter(old: Any, new: Any, now: float, lead: float, rate_hz: float, t_split: float) -> str:
        return control.SWAP_LATE if t_split < now + 1.0 else real(old, new, now, lead, rate_hz, t_split)

    monkeypatch.setattr(control, "swap_refusal", stricter)
    code, out = run(path, capsys)
    assert code == 1, out
    assert "first difference: swap 1 (mission m)" in line(out) and f"decided again {SWAP_LATE!r}" in line(out)


def test_a_removed_record_is_a_gap(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, _rec, _d = recorded(tmp_path / "rec")
    code, out = run(rewrite(path, tmp_path / "removed.mcap", lambda r: None if r["seq"] == 2 else r, topic=TOPIC),
                    capsys)
    assert code == 1, out
    assert line(out).startswith("swaps: 2 of 3 decided alike; first difference: seq 2 missing (1 record: dropped by "
                                "the recorder, or removed)")


def test_records_the_recorder_dropped_are_said(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path, rec, _d = recorded(tmp_path, queue=1, early=4)
    dropped = rec.dropped.get("swap", 0)
    assert dropped >= 3  # the first waited in the queue of one (later ones may find it full too)
    kept = [r["seq"] for r in swaps(path)]
    assert len(kept) == 7 - dropped and kept[0] == 1
    found, recorded_any = replay_swaps.replay_file(str(path))
    assert recorded_any and found.reproduced == len(kept)
    assert found.differences[-1].startswith(f"the recorder dropped {dropped} swap records in this run (its queue "
                                            "was full)")
    code, out = run(path, capsys)
    assert code == 1, out
    assert line(out).startswith(f"swaps: {len(kept)} of {kept[-1]} decided alike; first difference: seq 2 ") \
        and "missing" in line(out), line(out)


class _Evil:
    def __reduce__(self) -> Any:
        return (os.system, ("echo pwned > pwned.txt",))


def test_a_swap_record_cannot_name_anything_else(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.chdir(tmp_path)
    path, _rec, _d = recorded(tmp_path / "rec")

    def edit(r: dict[str, Any]) -> dict[str, Any]:
        return {**r, "pickle": base64.b64encode(pickle.dumps((_Evil(), _Evil()))).decode()}

    assert replay_cli.main([str(rewrite(path, tmp_path / "evil.mcap", edit, topic=TOPIC))]) == 2
    assert "replay does not load posix.system from a swap record" in capsys.readouterr().err
    assert not (tmp_path / "pwned.txt").exists()


def test_the_recorded_span_decides_as_the_whole_curves() -> None:
    """The recorder keeps only the segments from now to the split (`swap_span`): on them the rule
    decides as on the whole trajectories, for any moment and split, swapped in or refused."""
    from hypothesis import given, settings
    from hypothesis import strategies as st

    from companion.control import swap_refusal, swap_span

    route = fly([[3.0, 0.0, -1.5], [3.0, 3.0, -2.0], [0.0, 3.0, -1.5], [0.0, 0.0, -1.5]], HERE.tolist(), t0=0.0)
    old = route.trajectory
    assert old.n_segments >= 4
    bent = old.control_points.copy()
    bent[2, 5:] += 0.2  # differs from the third segment's middle on
    news = [old, type(old)(old.times, bent), hold(HERE, 0.0)]
    span = (old.t0 - 1.0, old.t_end + 1.0)
    seen: set[str] = set()

    @settings(max_examples=300, deadline=None)
    @given(now=st.floats(*span), ahead=st.floats(-0.5, 8.0), which=st.sampled_from([0, 1, 2]),
           lead=st.sampled_from([0.0, 0.06, 0.34]))
    def same(now: float, ahead: float, which: int, lead: float) -> None:
        new, t_split = news[which], now + ahead
        whole = swap_refusal(old, new, now, lead, 50.0, t_split)
        cut_old, cut_new = swap_span(old, now, t_split), swap_span(new, now, t_split)
        assert swap_refusal(cut_old, cut_new, now, lead, 50.0, t_split) == whole
        seen.add(whole)
        assert cut_old.n_segments <= old.n_segments

    same()
    assert {"", SWAP_LATE, SWAP_DIFFERS} <= seen, seen  # every outcome was decided on both
    # and a boundary: the split exactly where a segment starts
    t_b = float(old.times[2])
    for which in (0, 1):
        whole = swap_refusal(old, news[which], t_b - 0.5, 0.06, 50.0, t_b)
        assert swap_refusal(swap_span(old, t_b - 0.5, t_b), swap_span(news[which], t_b - 0.5, t_b), t_b - 0.5, 0.06,
                            50.0, t_b) == whole
