"""What the autopilot will follow, and the bounds the companion plans within because of it.

Pure: no I/O. The autopilot's own limits (read as parameters at link-up by the service,
`companion.wire.limits_params` names them) are an `AutopilotLimits`; the bounds flown are
the configured (or a mission's own) bounds clipped to those limits times a headroom, and
every clip is a `Clip` the service reports (order, axis, from, to, parameter).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import numpy as np

from companion.wire.limits_params import PROFILES, LimitParam
from planner_core import Bounds

G = 9.80665
ORDERS = ("velocity", "acceleration", "jerk", "snap")
AXES = ("x", "y", "z")


@dataclass(frozen=True)
class Limit:
    value: float  # SI (m/s, m/s/s, m/s/s/s, deg)
    source: str  # "param": read from the autopilot; "default": its stock default (not answered)
    param: str  # the parameter's name (as the autopilot answered, or the first tried)
    binds: bool = True  # the autopilot applies it to the companion's setpoints

    def as_dict(self) -> dict[str, Any]:
        return {"value": round(self.value, 4), "source": self.source, "param": self.param, "binds": self.binds}


@dataclass(frozen=True)
class AutopilotLimits:
    """The autopilot's limits on the setpoints it is streamed (NED: up is -z)."""

    autopilot: str
    horizontal_speed: Limit  # norm in the horizontal plane
    horizontal_accel: Limit
    up_speed: Limit
    down_speed: Limit
    up_accel: Limit
    down_accel: Limit
    horizontal_jerk: Limit | None = None  # None: the autopilot has none we know of
    vertical_jerk: Limit | None = None
    tilt: Limit | None = None  # deg: bounds the horizontal acceleration at g tan(tilt)

    def fields(self) -> dict[str, Limit]:
        out: dict[str, Limit] = {}
        for name in ("horizontal_speed", "horizontal_accel", "up_speed", "down_speed", "up_accel", "down_accel",
                     "horizontal_jerk", "vertical_jerk", "tilt"):
            lim = getattr(self, name)
            if lim is not None:
                out[name] = lim
        return out

    def defaulted(self) -> list[str]:
        """Parameters the autopilot did not answer for (their stock defaults stand in)."""
        return sorted({lim.param for lim in self.fields().values() if lim.source == "default"})

    def as_status(self) -> dict[str, Any]:
        return {"autopilot": self.autopilot, **{k: v.as_dict() for k, v in self.fields().items()}}

    def effective_horizontal_accel(self) -> Limit:
        """WPNAV_ACCEL / MPC_ACC_HOR_MAX, or less where the tilt limit allows less."""
        acc = self.horizontal_accel
        if self.tilt is not None and 0.0 < self.tilt.value < 90.0:
            by_tilt = G * math.tan(math.radians(self.tilt.value))
            if by_tilt < acc.value:
                return Limit(by_tilt, self.tilt.source, self.tilt.param, self.tilt.binds)
        return acc


def limits_from_params(autopilot: str, answered: dict[str, float]) -> AutopilotLimits | None:
    """The profile's limits from the parameters the autopilot answered (name -> value in its
    own unit); the stock default for each it did not. None for an autopilot with no profile."""
    profile = PROFILES.get(autopilot)
    if profile is None:
        return None
    values: dict[str, Limit] = {}
    for p in profile:
        values[p.field] = _limit(p, answered)
    return AutopilotLimits(autopilot=autopilot, **values)


def _limit(p: LimitParam, answered: dict[str, float]) -> Limit:
    for name in p.names:
        value = answered.get(name)
        if value is not None and math.isfinite(value) and value > 0.0:
            return Limit(value * p.scale, "param", name, p.binds)
    return Limit(p.default, "default", p.names[-1] if len(p.names) > 1 else p.names[0], p.binds)


@dataclass(frozen=True)
class Clip:
    """One bound the autopilot's limits lowered."""

    order: str  # "velocity" | "acceleration" | "jerk"
    axis: str  # "x" | "y" | "z" | "xy" (the horizontal norm)
    side: str  # "lo" | "hi" (NED: z lo is up) | "norm"
    was: float
    now: float
    param: str  # the parameter that set it
    source: str  # "param" | "default"

    def as_dict(self) -> dict[str, Any]:
        return {"order": self.order, "axis": self.axis, "side": self.side, "from": round(self.was, 4),
                "to": round(self.now, 4), "param": self.param, "source": self.source}

    def text(self) -> str:
        if self.side == "norm":
            return f"{self.order} horizontal {abs(self.was):.3g} -> {abs(self.now):.3g} ({self.param})"
        where = {"lo": "up" if self.axis == "z" else "-", "hi": "down" if self.axis == "z" else "+"}[self.side]
        return f"{self.order} {where}{self.axis} {abs(self.was):g} -> {abs(self.now):.3g} ({self.param})"


def limit_box(lim: AutopilotLimits, headroom: float) -> tuple[Bounds, np.ndarray]:
    """The autopilot's limits times `headroom` as planner bounds: the horizontal ones on the
    norm of the (x, y) part (`Bounds.horizontal`, certified on the inscribed polygon: autopilots
    limit the horizontal speed and acceleration as a norm, WPNAV_SPEED / MPC_XY_VEL_MAX), the
    vertical ones as the box's z row, asymmetric in NED (up is -z: up speed/accel bound z from
    below, down from above). Also which parameter set each entry: a (4, 4, 2) array of
    "param|source" strings, "" where unbounded; axis 3 is the horizontal norm (side 1)."""
    lo = np.full((4, 3), -np.inf)
    hi = np.full((4, 3), np.inf)
    horizontal = np.full(4, np.inf)
    who = np.full((4, 4, 2), "", dtype=object)

    def put(order: int, ax: int, side: int, value: float, src: Limit) -> None:
        if ax == 3:
            horizontal[order] = value
        elif side == 0:
            lo[order, ax] = -value
        else:
            hi[order, ax] = value
        who[order, ax, side] = f"{src.param}|{src.source}"

    hv, ha = lim.horizontal_speed, lim.effective_horizontal_accel()
    for order, src in ((0, hv), (1, ha), (2, lim.horizontal_jerk)):
        if src is not None and src.binds:
            put(order, 3, 1, src.value * headroom, src)
    for order, up, down in ((0, lim.up_speed, lim.down_speed), (1, lim.up_accel, lim.down_accel),
                            (2, lim.vertical_jerk, lim.vertical_jerk)):
        if up is not None and up.binds:
            put(order, 2, 0, up.value * headroom, up)
        if down is not None and down.binds:
            put(order, 2, 1, down.value * headroom, down)
    return Bounds(lo, hi, horizontal=horizontal), who


def clip_bounds(bounds: Bounds, lim: AutopilotLimits | None, headroom: float) -> tuple[Bounds, list[Clip]]:
    """`bounds` within the autopilot's limits x headroom (each entry the tighter of the two:
    the box entry by entry, the horizontal norm per order), and what was lowered. Unchanged
    without limits."""
    if lim is None:
        return bounds, []
    box, who = limit_box(lim, headroom)
    lo = np.maximum(bounds.lo, box.lo)
    hi = np.minimum(bounds.hi, box.hi)
    # what the configured bounds let the horizontal norm reach: their own norm bound, or the
    # corner of their x, y box
    reach = np.minimum(bounds.horizontal, np.hypot(np.maximum(-bounds.lo[:, 0], bounds.hi[:, 0]),
                                                   np.maximum(-bounds.lo[:, 1], bounds.hi[:, 1])))
    horizontal = np.minimum(bounds.horizontal, box.horizontal)
    clips: list[Clip] = []
    for order in range(4):
        for ax in range(3):
            for side, old, new in ((0, bounds.lo[order, ax], lo[order, ax]), (1, bounds.hi[order, ax], hi[order, ax])):
                if new != old:
                    param, source = str(who[order, ax, side]).split("|")
                    clips.append(Clip(ORDERS[order], AXES[ax], ("lo", "hi")[side], float(old), float(new),
                                      param, source))
        if box.horizontal[order] < reach[order]:
            param, source = str(who[order, 3, 1]).split("|")
            clips.append(Clip(ORDERS[order], "xy", "norm", float(reach[order]), float(box.horizontal[order]),
                              param, source))
    return Bounds(lo, hi, horizontal=horizontal, sides=bounds.sides), clips


def refusal_note(clips: list[Clip], headroom: float) -> str:
    """What a refusal for no plan within the bounds adds when the autopilot's limits lowered
    them: the parameters, each once, short enough to survive the event's bounded reason
    (the values are in the 'limits' event and status)."""
    if not clips:
        return ""
    params = list(dict.fromkeys(c.param for c in clips))
    return f" (planned within the autopilot's limits x headroom {headroom:g}, lowered by {', '.join(params)})"


def clips_text(clips: list[Clip]) -> str:
    """One line for an event: each clipped bound once (x and y together when they match)."""
    parts: list[str] = []
    seen: set[tuple[str, str, float, str]] = set()
    for c in clips:
        key = (c.order, c.side if c.axis in ("z", "xy") else "xy", round(abs(c.now), 6), c.param)
        if key in seen:
            continue
        seen.add(key)
        if c.axis in ("z", "xy"):
            parts.append(c.text())
        else:
            parts.append(f"{c.order} x/y {abs(c.was):g} -> {abs(c.now):.3g} ({c.param})")
    return "; ".join(parts)
