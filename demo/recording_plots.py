"""The demo's flight as the companion recorded it (out/demo/flight.mcap), in one figure.

Drawn from the recording alone, read with the `mcap` reader: what the companion commanded
(every setpoint sent), what the autopilot reported (LOCAL_POSITION_NED), the bounds each plan
was given, the tracking error the companion measured, and when it planned.
"""

from __future__ import annotations

import json
from collections import defaultdict
from pathlib import Path
from typing import Any

import numpy as np

from companion.wire.frames import swap_points


def read(path: Path) -> dict[str, list[dict[str, Any]]]:
    from mcap.reader import make_reader

    topics = ["/mavlink/out/SET_POSITION_TARGET_LOCAL_NED", "/mavlink/in/LOCAL_POSITION_NED", "/out/status",
              "/viz/bounds", "/planner/plan"]
    out: dict[str, list[dict[str, Any]]] = defaultdict(list)
    with open(path, "rb") as fh:
        for _s, channel, message in make_reader(fh).iter_messages(topics=topics):
            body = json.loads(message.data)
            body.pop("call", None)  # pickles: not needed here
            body.pop("result", None)
            body["_log_time"] = message.log_time / 1e9
            out[channel.topic].append(body)
    return out


def plot(path: Path, png: Path, title: str = "Flight, from the companion's recording") -> Path | None:
    rec = read(path)
    sp, pos = rec["/mavlink/out/SET_POSITION_TARGET_LOCAL_NED"], rec["/mavlink/in/LOCAL_POSITION_NED"]
    if not sp or not pos:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    t0 = min(sp[0]["t"], pos[0]["t"])
    sp_t = np.array([r["t"] for r in sp]) - t0
    sp_p = swap_points(np.array([[r["x"], r["y"], r["z"]] for r in sp]))
    sp_v = np.linalg.norm([[r["vx"], r["vy"], r["vz"]] for r in sp], axis=1)
    pos_t = np.array([r["t"] for r in pos]) - t0
    pos_p = swap_points(np.array([[r["x"], r["y"], r["z"]] for r in pos]))
    pos_v = np.linalg.norm([[r["vx"], r["vy"], r["vz"]] for r in pos], axis=1)
    # the recording's two clocks: `t` (monotonic) for MAVLink and plans, log time for status
    offset = sp[0]["_log_time"] - sp[0]["t"]

    fig, axes = plt.subplots(1, 3, figsize=(17, 5.2))
    ax = axes[0]
    ax.plot(sp_p[:, 0], sp_p[:, 1], lw=2.5, alpha=0.5, label="commanded (setpoints sent)")
    ax.plot(pos_p[:, 0], pos_p[:, 1], lw=1, color="k", label="reported by the autopilot")
    ax.set_aspect("equal")
    ax.set_xlabel("east [m] (local_enu)")
    ax.set_ylabel("north [m]")
    ax.set_title("top view")
    ax.legend(loc="best", fontsize=8)

    ax = axes[1]
    ax.plot(sp_t, sp_v, lw=2, alpha=0.6, label="|v| commanded")
    ax.plot(pos_t, pos_v, lw=1, color="k", label="|v| reported")
    bounds = rec["/viz/bounds"]
    if bounds:
        bt = np.array([b["t"] for b in bounds]) - t0
        bv = np.array([b["velocity"] if b["velocity"] is not None else np.nan for b in bounds])
        ax.step(np.append(bt, sp_t[-1]), np.append(bv, bv[-1]), where="post", color="r", ls="--",
                label="velocity bound given to the planner")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("speed [m/s]")
    ax.set_title("speed against the bounds")
    ax.legend(loc="best", fontsize=8)

    ax = axes[2]
    st = [(s["_log_time"] - offset - t0, s.get("tracking_error")) for s in rec["/out/status"]]
    st = [(t, e) for t, e in st if isinstance(e, int | float)]
    if st:
        ax.plot([t for t, _ in st], [e for _, e in st], color="k", label="tracking error (companion, status)")
    plans = rec["/planner/plan"]
    ax2 = ax.twinx()
    if plans:
        ax2.scatter([p["done"] - t0 for p in plans], [p["latency_ms"] for p in plans], marker="o",
                    c=["tab:green" if p.get("ok") else "tab:red" for p in plans], s=18)
    ax2.set_ylabel("plan latency [ms] (dots; red: not ok)")
    ax.set_xlabel("time [s]")
    ax.set_ylabel("tracking error [m]")
    ax.set_title("tracking and planning")
    if st:
        ax.legend(loc="upper left", fontsize=8)
    fig.suptitle(f"{title}: {path.name}")
    fig.tight_layout()
    fig.savefig(png, dpi=110)
    plt.close(fig)
    return png
