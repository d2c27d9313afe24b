"""The mock autopilot's configuration (`MockConfig`) and the constants its parts share: default
stream rates, ArduPilot's stream groups, PX4's event enums, timings."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

from pymavlink.dialects.v20 import common as mav

from .faults import FaultSpec
from .vehicle import VehicleParams

# Default stream rates (Hz) of the PX4 flavour, about what PX4 streams on a MAVLink instance in
# Onboard mode (the mode of PX4 SITL's offboard link, udp 14580 -> 14540); SET_MESSAGE_INTERVAL
# changes them. The ArduPilot flavour sends only HEARTBEAT until asked (APM_GROUPS).
DEFAULT_RATES: dict[int, float] = {
    mav.MAVLINK_MSG_ID_HEARTBEAT: 1.0,
    mav.MAVLINK_MSG_ID_SYS_STATUS: 2.0,
    mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED: 30.0,
    mav.MAVLINK_MSG_ID_ATTITUDE: 30.0,
    mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT: 10.0,
    mav.MAVLINK_MSG_ID_GPS_RAW_INT: 2.0,
    mav.MAVLINK_MSG_ID_EXTENDED_SYS_STATE: 5.0,
    mav.MAVLINK_MSG_ID_HOME_POSITION: 0.5,
    mav.MAVLINK_MSG_ID_GPS_GLOBAL_ORIGIN: 0.1,
    mav.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED: 10.0,
    mav.MAVLINK_MSG_ID_SYSTEM_TIME: 1.0,
}
# ArduPilot: the legacy stream groups (REQUEST_DATA_STREAM) of the messages the mock sends,
# with the parameter that sets each group's rate at boot. EXTENDED_SYS_STATE, HOME_POSITION
# and SYSTEM_TIME... are in no group here: on request only (SET_MESSAGE_INTERVAL / REQUEST_MESSAGE).
APM_GROUPS: dict[int, tuple[str, tuple[int, ...]]] = {
    mav.MAV_DATA_STREAM_EXTENDED_STATUS: ("MAV1_EXT_STAT", (mav.MAVLINK_MSG_ID_SYS_STATUS, mav.MAVLINK_MSG_ID_GPS_RAW_INT,
                                                            mav.MAVLINK_MSG_ID_POSITION_TARGET_LOCAL_NED)),
    mav.MAV_DATA_STREAM_POSITION: ("MAV1_POSITION", (mav.MAVLINK_MSG_ID_GLOBAL_POSITION_INT,
                                                     mav.MAVLINK_MSG_ID_LOCAL_POSITION_NED)),
    mav.MAV_DATA_STREAM_EXTRA1: ("MAV1_EXTRA1", (mav.MAVLINK_MSG_ID_ATTITUDE,)),
    mav.MAV_DATA_STREAM_EXTRA3: ("MAV1_EXTRA3", (mav.MAVLINK_MSG_ID_SYSTEM_TIME,)),
}
REBOOT_SILENCE_S = 3.0
# The ground's z in the local frame when not configured: PX4's estimator origin sits above the
# ground (z +1.5 to +1.7 m, NED, on a PX4 1.15 SIH SITL's ground); ArduPilot's is on it.
DEFAULT_GROUND_Z = {"px4": 1.6, "ardupilot": 0.0}
# PX4's events enums (arm_disarm_reason_t, failsafe_action_t), for the EVENT arguments.
ARM_REASON = {"command": 4, "auto-disarm after landing": 7, "auto-disarm: no takeoff": 8, "forced": 4,
              "failsafe": 15}
FAILSAFE_ACTION = {"LOITER": 5, "RTL": 6, "LAND": 7, "disarm": 9, "terminate": 10}
STREAM_GAP_S = 0.55  # a 2 Hz stream has 0.5 s gaps; allow a little jitter


@dataclass
class MockConfig:
    autopilot: str = "px4"
    endpoints: list[str] = field(default_factory=lambda: ["udpin:127.0.0.1:14540"])
    sysid: int = 1
    compid: int = 1
    log_path: str | None = None
    speed: float = 1.0
    control: str | None = None
    faults: FaultSpec = field(default_factory=FaultSpec)
    rate_hz: float = 250.0
    log_rate_hz: float | None = None  # None: every simulation step
    home_lat: float = 47.397742
    home_lon: float = 8.545594
    home_alt: float = 488.0
    seed: int | None = None
    wind: tuple[float, float, float] = (0.0, 0.0, 0.0)
    noise: float = 0.0  # std of reported position (m); velocity gets half of it in m/s
    takeovers: list[tuple[float, str]] = field(default_factory=list)
    params: dict[str, float] = field(default_factory=dict)
    offboard_warmup_s: float = 1.0
    # the vehicle's response, one of sitl_mock.vehicle.RESPONSES; None: the flavour's
    # (DEFAULT_RESPONSE: px4 "px4_sih", ardupilot "calibrated")
    vehicle: VehicleParams | None = None
    # MAVLink 2 signing: with a 32-byte key, unsigned or wrongly signed commands and setpoints
    # are ignored (logged as event "signature_rejected"), and everything the mock sends is
    # signed with it (as ArduPilot and PX4 do on a link with signing enabled) unless
    # sign_outgoing is False (an autopilot that checks but signs nothing).
    signing_key: bytes | None = None
    sign_outgoing: bool = True
    # z (NED, m) of the ground in the local frame; None: the flavour's (PX4 +1.6, ArduPilot 0).
    ground_z: float | None = None
    # PX4: report with STATUSTEXT as PX4 < 1.14 did, instead of EVENT messages.
    px4_statustext: bool = False
    # --- ArduPilot strictness and shaping (sitl_mock.ardupilot, sitl_mock.shaping)
    # Throttle pwm the autopilot receives: 1000 is what SITL sends with no transmitter (stick
    # down: pilot modes descend); 1500 mid-stick; None: no RC ever seen.
    rc_throttle: int | None = 1000
    # ArduPilot: seconds after boot until the EKF origin is set (stock SITL: 43 s after its start).
    ekf_origin_delay_s: float = 40.0
    # ArduPilot: seconds from the EKF origin (and home) to the first LOCAL_POSITION_NED (stock
    # ArduCopter 4.6 SITL, measured 2026-12-02: home and origin ~22 s before the first one).
    position_after_origin_s: float = 22.0
    # ArduPilot: how far (m, north and east) the position estimate on the ground moves between
    # the EKF origin (home set there) and arming (home set again where the estimate then is): stock
    # ArduCopter 4.6 SITL, measured 2026-12-02, home moved to [-0.011, 0.008, 0.010] m at arming.
    # The mock's ground is a plane (truth and estimate are one), so the 1 cm down is not copied.
    home_shift_at_arming: tuple[float, float] = (-0.011, 0.008)
    # ArduPilot: seconds after arming before any climb (stock SITL: 3.0 s).
    spool_up_s: float = 3.0
    # Shape targets with the autopilot's own limits (ArduCopter GUIDED: WPNAV_*; PX4: MPC_*).
    shaping: bool = True
    # PX4: seconds from boot until the estimator has settled and arming is allowed (sitl_mock.px4);
    # None: sitl_mock.px4.DEFAULT_READY_S (36.5 s, as PX4 1.15 SIH); 0: ready at boot.
    px4_ready_s: float | None = None
    # PX4: a period of arming-check reports while not ready, besides those PX4 sends when its
    # checks change (sitl_mock.px4.REPORTS_AT); None: none (as PX4). Tests about the words, not
    # the timing, set one.
    px4_report_every_s: float | None = None
    # PX4: how far (m) the estimate on the ground drifts horizontally by the time it is ready
    # (sitl_mock.px4.DRIFT_XY_M: 30, measured 23-42 m); None: that default; 0: no drift.
    px4_drift_m: float | None = None

    def validate(self) -> None:
        if self.autopilot not in ("px4", "ardupilot"):
            raise ValueError(f"autopilot: must be 'px4' or 'ardupilot', got {self.autopilot!r}")
        for name in ("sysid", "compid"):
            v = getattr(self, name)
            if not 1 <= v <= 255:
                raise ValueError(f"{name}: must be in 1..255, got {v}")
        if not self.speed > 0:
            raise ValueError(f"speed: must be > 0, got {self.speed}")
        if self.rate_hz < 200:
            raise ValueError(f"rate_hz: must be >= 200, got {self.rate_hz}")
        if not self.endpoints:
            raise ValueError("endpoints: at least one endpoint is needed")
        if self.px4_ready_s is not None and not (math.isfinite(self.px4_ready_s) and self.px4_ready_s >= 0):
            raise ValueError(f"px4_ready_s: must be a finite number of seconds >= 0, got {self.px4_ready_s}")
        if self.px4_report_every_s is not None and not (math.isfinite(self.px4_report_every_s)
                                                        and self.px4_report_every_s > 0):
            raise ValueError(f"px4_report_every_s: must be a finite number of seconds > 0, got {self.px4_report_every_s}")
        if self.px4_drift_m is not None and not (math.isfinite(self.px4_drift_m) and 0.0 <= self.px4_drift_m <= 1000.0):
            raise ValueError(f"px4_drift_m: must be a finite distance in [0, 1000] m, got {self.px4_drift_m}")
        if self.ground_z is not None and not (math.isfinite(self.ground_z) and abs(self.ground_z) <= 1000.0):
            raise ValueError(f"ground_z: must be a finite z in [-1000, 1000] m, got {self.ground_z}")
        if self.rc_throttle is not None and not 800 <= self.rc_throttle <= 2200:
            raise ValueError(f"rc_throttle: must be a pwm in 800..2200 or None (no RC), got {self.rc_throttle}")
        if len(self.home_shift_at_arming) != 2 or not all(
                math.isfinite(v) and abs(v) <= 10.0 for v in self.home_shift_at_arming):
            raise ValueError(f"home_shift_at_arming: must be 2 finite metres (north, east) within 10 m, "
                             f"got {self.home_shift_at_arming}")
        for name in ("ekf_origin_delay_s", "spool_up_s", "position_after_origin_s"):
            v = getattr(self, name)
            if not (math.isfinite(v) and v >= 0.0):
                raise ValueError(f"{name}: must be a finite number of seconds >= 0, got {v}")

    @property
    def resolved_ground_z(self) -> float:
        return DEFAULT_GROUND_Z[self.autopilot] if self.ground_z is None else float(self.ground_z)
