"""Point-mass quadrotor in local NED with a cascaded position/velocity controller.

z is down; the ground is the plane z = ``ground_z`` (0 unless set: PX4's local origin is
where its estimator started, usually above the ground) and the vehicle can never go below it.
"""

from __future__ import annotations

import collections
import math
from dataclasses import dataclass, field

import numpy as np

G = 9.80665


@dataclass(frozen=True)
class VehicleParams:
    kp_pos: float = 1.2  # 1/s, position error -> velocity command
    kv_vel: float = 5.0  # 1/s, velocity error -> acceleration command (damping ~1)
    tau_acc: float = 0.04  # s, first-order lag of the achieved acceleration
    max_tilt_deg: float = 35.0
    max_jerk: float = 40.0  # m/s^3, rate limit on the achieved acceleration
    max_speed_xy: float = 12.0
    max_climb: float = 3.0  # m/s up
    max_descent: float = 1.5  # m/s down
    max_acc_up: float = 6.0  # m/s^2 net upward acceleration
    max_yaw_rate: float = math.radians(90.0)
    drag: float = 0.3  # 1/s: wind speed (m/s) -> disturbance acceleration
    # How much of a commanded acceleration feed-forward the controller uses (1: all of it).
    acc_ff_gain: float = 1.0
    # s: a target takes this long to reach the controller (estimator and control latency).
    delay: float = 0.0
    # 1/s²: the horizontal velocity loop's integral gain (PX4 MPC_XY_VEL_I_ACC); 0: none
    ki_vel: float = 0.0
    # 1/s: the vehicle's own horizontal drag, which only that integral makes up for (PX4 SIH's
    # quad: SIH_KDV / SIH_MASS); 0: taken as compensated at once
    drag_xy: float = 0.0

    @property
    def max_acc_xy(self) -> float:
        return G * math.tan(math.radians(self.max_tilt_deg))


@dataclass(frozen=True)
class Limits:
    """Velocity and tilt limits that the autopilot's parameters set in flight (``shaping.py``),
    in place of the response's own; inf: no limit of that kind."""

    speed_xy: float
    climb: float
    descent: float
    tilt_deg: float


@dataclass
class Target:
    """Per-axis target; NaN means the axis is not commanded at that level."""

    pos: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    vel: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    acc: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    yaw: float = math.nan
    yaw_rate: float = math.nan

    @staticmethod
    def hold(pos: np.ndarray, yaw: float) -> Target:
        return Target(pos.astype(float).copy(), np.zeros(3), np.zeros(3), yaw, math.nan)

    def copy(self) -> Target:
        return Target(self.pos.copy(), self.vel.copy(), self.acc.copy(), self.yaw, self.yaw_rate)


@dataclass
class VehicleState:
    pos: np.ndarray = field(default_factory=lambda: np.zeros(3))
    vel: np.ndarray = field(default_factory=lambda: np.zeros(3))
    acc: np.ndarray = field(default_factory=lambda: np.zeros(3))
    yaw: float = 0.0
    yaw_rate: float = 0.0
    on_ground: bool = True


def sqrt_controller(error: float, kp: float, accel: float) -> float:
    """Velocity for a position error: linear near zero, braking-distance limited far away.

    The same shape as ArduPilot's sqrt_controller: a pure P gain would command speeds that
    the acceleration limit cannot stop from in time, and overshoot large steps.
    """
    linear = accel / (kp * kp)
    mag = abs(error)
    if mag <= linear:
        return kp * error
    return math.copysign(math.sqrt(2.0 * accel * (mag - 0.5 * linear)), error)


def _clip_norm(v: np.ndarray, limit: float) -> np.ndarray:
    n = float(np.hypot(v[0], v[1]))
    if n > limit > 0.0:
        v = v.copy()
        v[:2] *= limit / n
    return v


# Vehicle responses (`--response`). `ideal`: the controller follows a full feed-forward at
# once (tracking RMS ~0.012 m on the demo's scenario 1): for fast unit tests. `calibrated`
# (default): fitted to ArduCopter 4.7 SITL flying the demo's scenarios through the companion
# (issue 11: tracking RMS / max 0.136 / 0.235 m, effective lag 57 ms, 0.092 m with the lag
# removed); simulating the demo's scenario-1 trajectory through this model gives 0.138 /
# 0.253 m, lag 60 ms, 0.089 m with it removed (peak speed 3.2 m/s).
# `px4_sih` (the PX4 flavour's default): PX4 1.15 SIH followed pos+vel+acc setpoints with a
# best-fit lag of 0.31-0.38 s (/work/shared/autopilot-facts.md). PX4's default position and
# velocity gains (MPC_XY_P 0.95, MPC_XY_VEL_P_ACC 1.8), targets 0.3 s late, 70 % of the
# acceleration feed-forward used: level circles at 1.0 / 3.0 / 3.4 m/s simulated through it have
# a best-fit lag of 0.31 / 0.34 / 0.35 s and 0.03 / 0.24 / 0.30 m RMS with the lag removed.
# `px4_sih_drag`: what PX4 SIH's quad does that `px4_sih` does not: its first-order drag
# (sih.cpp: F = -SIH_KDV v, SIH_KDV 1.0 N/(m/s), SIH_MASS 1.0 kg) is made up for only by PX4's
# velocity integral (MPC_XY_VEL_I_ACC 0.4), so after the plan accelerates the vehicle falls behind
# for seconds. With PX4's gains, 70 % of the acceleration feed-forward and 75 ms of delay, the
# demo's scenario 1 flown through it with a 0.33 s lead trails the plan by -0.25 v - 0.90 F1 +
# 3.42 F4 (F_tc the plan's acceleration low-passed over tc s; 0.44 m RMS), where PX4 SIH flew
# -0.25 v - 0.95 F1 + 3.40 F4 (0.46-0.58 m RMS; docs/autopilot-limits.md). Not yet the PX4
# flavour's default: the PX4 tests and the demo are sized for `px4_sih`.
RESPONSES: dict[str, VehicleParams] = {
    "ideal": VehicleParams(),
    "calibrated": VehicleParams(kp_pos=1.0, kv_vel=4.0, tau_acc=0.08, acc_ff_gain=0.5, delay=0.03),
    "px4_sih": VehicleParams(kp_pos=0.95, kv_vel=1.8, tau_acc=0.08, acc_ff_gain=0.7, delay=0.3),
    "px4_sih_drag": VehicleParams(kp_pos=0.95, kv_vel=1.8, tau_acc=0.08, acc_ff_gain=0.7, delay=0.075, ki_vel=0.4,
                                  drag_xy=1.0),
}
# Each flavour's response when none is chosen.
DEFAULT_RESPONSE = {"px4": "px4_sih", "ardupilot": "calibrated"}


class Vehicle:
    def __init__(self, params: VehicleParams | None = None, ground_z: float = 0.0) -> None:
        self.params = params or RESPONSES["calibrated"]
        self.ground_z = float(ground_z)
        self.state = VehicleState(pos=np.array([0.0, 0.0, self.ground_z]))
        self.acc_cmd = np.zeros(3)
        self._t = 0.0
        self._pending: collections.deque[tuple[float, Target | None]] = collections.deque()
        self._applied: Target | None = None
        # --- shaping hook: set each step by the server (None: the response's own limits)
        self.limits: Limits | None = None
        self._vel_int = np.zeros(3)  # the velocity loop's integral (horizontal; ki_vel)
        self._dt = 0.0

    def _delayed(self, dt: float, target: Target | None) -> Target | None:
        """The target as the controller sees it, `delay` seconds late."""
        self._t += dt
        if self.params.delay <= 0.0:
            return target
        self._pending.append((self._t, None if target is None else target.copy()))
        while self._pending and self._pending[0][0] <= self._t - self.params.delay + 1e-12:
            self._applied = self._pending.popleft()[1]
        return self._applied if self._applied is not None else target

    def reset(self, pos: np.ndarray | None = None) -> None:
        self.state = VehicleState(pos=np.array([0.0, 0.0, self.ground_z]))
        self._pending.clear()
        self._applied = None
        self._vel_int = np.zeros(3)
        if pos is not None:
            self.state.pos = pos.astype(float).copy()
        self.acc_cmd = np.zeros(3)

    def _command(self, target: Target) -> np.ndarray:
        p, s = self.params, self.state
        lim = self.limits
        speed_xy = p.max_speed_xy if lim is None else lim.speed_xy
        climb = p.max_climb if lim is None else lim.climb
        descent = p.max_descent if lim is None else lim.descent
        acc_xy = p.max_acc_xy if lim is None else G * math.tan(math.radians(lim.tilt_deg))
        has_pos = np.isfinite(target.pos)
        has_vel = np.isfinite(target.vel)
        vel_ff = np.where(has_vel, target.vel, 0.0)
        err = np.where(has_pos, np.nan_to_num(target.pos) - s.pos, 0.0)
        n_xy = float(np.hypot(err[0], err[1]))
        v_p = np.zeros(3)
        if n_xy > 0.0:
            v_p[:2] = err[:2] * (sqrt_controller(n_xy, p.kp_pos, 0.5 * acc_xy) / n_xy)
        v_p[2] = sqrt_controller(float(err[2]), p.kp_pos, 0.5 * p.max_acc_up)
        v_cmd = np.where(has_pos, v_p + vel_ff, vel_ff)
        v_cmd = _clip_norm(v_cmd, speed_xy)
        v_cmd[2] = min(max(v_cmd[2], -climb), descent)
        # An axis with neither position nor velocity is driven by its acceleration only.
        vel_loop = has_pos | has_vel
        acc_ff = np.where(np.isfinite(target.acc), target.acc * p.acc_ff_gain, 0.0)
        damp = np.where(np.isfinite(target.acc), 0.0, -p.kv_vel * s.vel)
        a_cmd = np.where(vel_loop, p.kv_vel * (v_cmd - s.vel) + acc_ff, acc_ff + damp)
        if p.ki_vel > 0.0:
            if s.on_ground:
                self._vel_int[:] = 0.0  # as PX4 resets its integrators when landed
            elif vel_loop[0] and vel_loop[1]:
                self._vel_int[:2] = _clip_norm(self._vel_int + p.ki_vel * (v_cmd - s.vel) * self._dt, acc_xy)[:2]
            a_cmd = a_cmd + self._vel_int
        a_cmd = _clip_norm(a_cmd, acc_xy)
        # Thrust cannot pull down: net downward acceleration is at most g.
        a_cmd[2] = min(max(a_cmd[2], -p.max_acc_up), G)
        return a_cmd

    def step(self, dt: float, target: Target | None, armed: bool, wind: np.ndarray) -> None:
        p, s = self.params, self.state
        self._dt = dt
        target = self._delayed(dt, target)
        # Motors off: free fall (or resting on the ground).
        a_cmd = self._command(target) if armed and target is not None else np.array([0.0, 0.0, G])
        self.acc_cmd = a_cmd
        alpha = min(1.0, dt / p.tau_acc) if armed else 1.0
        delta = (a_cmd - s.acc) * alpha
        if armed:
            dn = float(np.linalg.norm(delta))
            lim = p.max_jerk * dt
            if dn > lim:
                delta *= lim / dn
        s.acc = s.acc + delta
        # Wind is a constant push; the vehicle's own drag is taken as compensated by the
        # autopilot, as PX4/ArduPilot do with their velocity-loop integrators.
        total = s.acc + p.drag * wind if armed and not s.on_ground else s.acc
        if p.drag_xy > 0.0 and not s.on_ground:
            total = total - p.drag_xy * np.array([s.vel[0], s.vel[1], 0.0])
        s.vel = s.vel + total * dt
        s.pos = s.pos + s.vel * dt
        g = self.ground_z
        if s.pos[2] >= g:
            s.pos[2] = g
            s.vel[2] = min(s.vel[2], 0.0)
            if s.acc[2] >= 0.0 or not armed:
                # Resting on the ground: friction stops horizontal motion.
                s.vel[:] = 0.0
                s.acc[2] = min(s.acc[2], 0.0) if armed else 0.0
        s.on_ground = bool(s.pos[2] >= g - 0.02 and s.vel[2] >= -0.05 and self.acc_cmd[2] >= -0.05)
        self._step_yaw(dt, target if armed else None)

    def _step_yaw(self, dt: float, target: Target | None) -> None:
        p, s = self.params, self.state
        rate = 0.0
        if target is not None and not s.on_ground:
            if math.isfinite(target.yaw):
                err = math.atan2(math.sin(target.yaw - s.yaw), math.cos(target.yaw - s.yaw))
                rate = 4.0 * err
            elif math.isfinite(target.yaw_rate):
                rate = target.yaw_rate
        rate = min(max(rate, -p.max_yaw_rate), p.max_yaw_rate)
        s.yaw_rate = rate
        s.yaw = math.atan2(math.sin(s.yaw + rate * dt), math.cos(s.yaw + rate * dt))

    def attitude(self) -> tuple[float, float, float]:
        """Roll, pitch, yaw from the thrust direction needed for the achieved acceleration."""
        s = self.state
        c, sn = math.cos(s.yaw), math.sin(s.yaw)
        fwd = c * s.acc[0] + sn * s.acc[1]
        right = -sn * s.acc[0] + c * s.acc[1]
        up = G - s.acc[2]
        pitch = -math.atan2(fwd, up)
        roll = math.atan2(right * math.cos(pitch), up)
        return roll, pitch, s.yaw
