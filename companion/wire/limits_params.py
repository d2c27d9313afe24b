"""The autopilots' own speed and acceleration limits on the targets the companion streams:
which parameter holds each, in which unit, and the stock default (used, and said, when the
autopilot does not answer for it).

One profile per autopilot; `companion.limits` holds the logic. Each entry lists the names
to try, newest first: the first one the autopilot answers for is the one it has.

ArduCopter (GUIDED position-velocity-acceleration targets are shaped with these:
`ArduCopter/mode_guided.cpp` `pva_control_start`, `libraries/AC_WPNav/AC_WPNav.cpp`,
`libraries/AC_AttitudeControl/AC_PosControl.cpp`):
- `WPNAV_SPEED`, `WPNAV_SPEED_UP`, `WPNAV_SPEED_DN` (cm/s), `WPNAV_ACCEL`, `WPNAV_ACCEL_Z`
  (cm/s/s): the same names and units from 4.0 to master (AC_WPNav var_info);
- the shaping jerk `PSC_JERK_XY` / `PSC_JERK_Z` (m/s/s/s, 4.1 to 4.6), renamed `PSC_JERK_NE`
  / `PSC_JERK_D` on master (AC_PosControl var_info, same index 10 / 11, same unit).
PX4 (`src/modules/mc_pos_control/*_params.c`, SI units): `MPC_XY_VEL_MAX`,
`MPC_Z_VEL_MAX_UP`, `MPC_Z_VEL_MAX_DN` (m/s), `MPC_ACC_HOR_MAX`, `MPC_ACC_UP_MAX`,
`MPC_ACC_DOWN_MAX` (m/s/s), `MPC_JERK_MAX` (m/s/s/s), `MPC_TILTMAX_AIR` (deg). PX4's jerk
limit shapes its own auto-mode trajectories (FlightTaskAuto), not offboard setpoints, so it
is read and shown but does not bind (`binds` False); the tilt limit bounds the horizontal
acceleration the controller can give at all (g tan(tilt)), which the profile also reads.
"""

from __future__ import annotations

from dataclasses import dataclass

CM = 0.01  # cm -> m


@dataclass(frozen=True)
class LimitParam:
    field: str  # companion.limits.AutopilotLimits field
    names: tuple[str, ...]  # tried newest first
    scale: float  # SI per unit of the parameter
    default: float  # SI: the autopilot's stock default, used when no name is answered
    unit: str  # the parameter's own unit, for what the companion says
    binds: bool = True  # the autopilot applies it to the companion's setpoints


ARDUPILOT: tuple[LimitParam, ...] = (
    LimitParam("horizontal_speed", ("WPNAV_SPEED",), CM, 10.0, "cm/s"),
    LimitParam("horizontal_accel", ("WPNAV_ACCEL",), CM, 2.5, "cm/s/s"),
    LimitParam("up_speed", ("WPNAV_SPEED_UP",), CM, 2.5, "cm/s"),
    LimitParam("down_speed", ("WPNAV_SPEED_DN",), CM, 1.5, "cm/s"),
    LimitParam("up_accel", ("WPNAV_ACCEL_Z",), CM, 1.0, "cm/s/s"),
    LimitParam("down_accel", ("WPNAV_ACCEL_Z",), CM, 1.0, "cm/s/s"),
    LimitParam("horizontal_jerk", ("PSC_JERK_NE", "PSC_JERK_XY"), 1.0, 5.0, "m/s/s/s"),
    LimitParam("vertical_jerk", ("PSC_JERK_D", "PSC_JERK_Z"), 1.0, 5.0, "m/s/s/s"),
)

PX4: tuple[LimitParam, ...] = (
    LimitParam("horizontal_speed", ("MPC_XY_VEL_MAX",), 1.0, 12.0, "m/s"),
    LimitParam("horizontal_accel", ("MPC_ACC_HOR_MAX",), 1.0, 5.0, "m/s/s"),
    LimitParam("up_speed", ("MPC_Z_VEL_MAX_UP",), 1.0, 3.0, "m/s"),
    LimitParam("down_speed", ("MPC_Z_VEL_MAX_DN",), 1.0, 1.5, "m/s"),
    LimitParam("up_accel", ("MPC_ACC_UP_MAX",), 1.0, 4.0, "m/s/s"),
    LimitParam("down_accel", ("MPC_ACC_DOWN_MAX",), 1.0, 3.0, "m/s/s"),
    LimitParam("horizontal_jerk", ("MPC_JERK_MAX",), 1.0, 8.0, "m/s/s/s", binds=False),
    LimitParam("vertical_jerk", ("MPC_JERK_MAX",), 1.0, 8.0, "m/s/s/s", binds=False),
    LimitParam("tilt", ("MPC_TILTMAX_AIR",), 1.0, 45.0, "deg"),
)

PROFILES: dict[str, tuple[LimitParam, ...]] = {"ardupilot": ARDUPILOT, "px4": PX4}


def names_to_read(autopilot: str) -> list[str]:
    """Every parameter name of the autopilot's profile, once each, in profile order."""
    out: list[str] = []
    for p in PROFILES.get(autopilot, ()):
        for n in p.names:
            if n not in out:
                out.append(n)
    return out
