"""The mock autopilot's MAVLink command and message handlers (`MavlinkHandlers`): COMMAND_LONG /
COMMAND_INT, SET_MODE, setpoints, parameters, stream requests, mission list, TIMESYNC.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Any, cast

import numpy as np
from pymavlink.dialects.v20 import common as mav

from . import px4
from . import telemetry as tm
from .protocol import FORCE_SET_MAGIC, Flavour, Param, decode_setpoint, target_matches
from .server_config import DEFAULT_RATES, STREAM_GAP_S
from .server_step import Simulation
from .vehicle import Target

if TYPE_CHECKING:
    # the flavour rules (sitl_mock.ardupilot) take the whole autopilot; this class is one layer
    # of it, so `self` is handed over as what it is at run time
    from .server import MockAutopilot


class MavlinkHandlers(Simulation):
    """Incoming MAVLink, one handler per message type."""

    # ------------------------------------------------------------------ incoming MAVLink

    def _on_message(self, msg: Any) -> None:
        kind = msg.get_type()
        handler = {
            "COMMAND_LONG": self._on_command_long,
            "COMMAND_INT": self._on_command_int,
            "SET_MODE": self._on_set_mode,
            "SET_POSITION_TARGET_LOCAL_NED": self._on_setpoint,
            "PARAM_REQUEST_LIST": self._on_param_list,
            "PARAM_REQUEST_READ": self._on_param_read,
            "PARAM_SET": self._on_param_set,
            "MISSION_REQUEST_LIST": self._on_mission_list,
            "TIMESYNC": self._on_timesync,
            "REQUEST_DATA_STREAM": self._on_request_data_stream,
            "FILE_TRANSFER_PROTOCOL": self.px4.on_ftp if self.px4 is not None else None,
        }.get(kind)
        if handler is None:
            return
        try:
            handler(msg)
        except Exception as exc:  # a malformed packet must not take the autopilot down
            self.log.write("event", self.t, event="handler_error", message=kind, error=repr(exc))
        self._update_snapshot()

    def _for_us(self, msg: Any) -> bool:
        return target_matches(msg.target_system, msg.target_component, self.config.sysid, self.config.compid)

    def _on_command_long(self, msg: Any) -> None:
        if not self._for_us(msg):
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, msg.param5, msg.param6, msg.param7)
        self._command(msg, int(msg.command), params)

    def _on_command_int(self, msg: Any) -> None:
        if not self._for_us(msg):
            return
        params = (msg.param1, msg.param2, msg.param3, msg.param4, float(msg.x), float(msg.y), msg.z)
        self._command(msg, int(msg.command), params)

    def _command(self, msg: Any, command: int, p: tuple[float, ...]) -> None:
        result, why = self._dispatch_command(command, p)
        self.log.write("event", self.t, event="command", command=command, params=list(p),
                       result=result, reason=why)
        self._update_snapshot()  # so that whoever sees the ACK sees its effect too
        self._send(self.enc.mav.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(),
                                                   msg.get_srcComponent()))
        if self._reboot_pending:
            self._reboot_pending = False
            self.reboot()

    def _dispatch_command(self, command: int, p: tuple[float, ...]) -> tuple[int, str]:
        if command == mav.MAV_CMD_COMPONENT_ARM_DISARM:
            force = _int(p[1]) == FORCE_SET_MAGIC
            return self.arm(force) if p[0] >= 0.5 else self.disarm(force)
        if command == mav.MAV_CMD_DO_SET_MODE:
            return self._do_set_mode(_int(p[0]), _int(p[1]), _int(p[2]))
        if command == mav.MAV_CMD_NAV_TAKEOFF:
            return self.takeoff(float(p[6]))
        if command == mav.MAV_CMD_NAV_LAND:
            return self.request_mode("LAND", "land command")
        if command == mav.MAV_CMD_NAV_RETURN_TO_LAUNCH:
            return self.request_mode(self.modes.canonical("RTL"), "rtl command")
        if command == mav.MAV_CMD_SET_MESSAGE_INTERVAL:
            return self._set_interval(_int(p[0]), float(p[1]))
        if command == mav.MAV_CMD_REQUEST_MESSAGE:
            return self._request_message(_int(p[0]))
        if command == mav.MAV_CMD_PREFLIGHT_REBOOT_SHUTDOWN and _int(p[0]) == 1:
            if self.armed:
                return self._refuse(), "reboot refused: armed"
            # Acknowledged first, as the autopilot does before it goes quiet.
            self._reboot_pending = True
            return int(mav.MAV_RESULT_ACCEPTED), ""
        if command == mav.MAV_CMD_GET_HOME_POSITION:  # deprecated for REQUEST_MESSAGE, still answered
            return self._request_message(mav.MAVLINK_MSG_ID_HOME_POSITION)
        if command == mav.MAV_CMD_REQUEST_AUTOPILOT_CAPABILITIES:
            return self._request_message(mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION)
        return int(mav.MAV_RESULT_UNSUPPORTED), f"command {command} unsupported"

    def _do_set_mode(self, base: int, main: int, sub: int) -> tuple[int, str]:
        if not base & mav.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED:
            return int(mav.MAV_RESULT_UNSUPPORTED), "base mode without custom mode flag"
        name = self.modes.from_custom(main, sub)
        if name is None:
            why = f"unknown custom mode {main}/{sub}"
            self._report(mav.MAV_SEVERITY_WARNING, why, None)
            return self._refuse(), why
        result, why = self.request_mode(name, "command")
        if result != mav.MAV_RESULT_ACCEPTED and self.flavour is Flavour.ARDUPILOT:
            result = int(mav.MAV_RESULT_FAILED)
        return result, why

    def _on_set_mode(self, msg: Any) -> None:
        if msg.target_system not in (0, self.config.sysid):
            return
        result, _ = self._do_set_mode(int(msg.base_mode), *self._split_custom(int(msg.custom_mode)))
        # PX4 acks a SET_MODE as the DO_SET_MODE it turns it into; ArduPilot acks message id 11.
        command = mav.MAV_CMD_DO_SET_MODE if self.flavour is Flavour.PX4 else mav.MAVLINK_MSG_ID_SET_MODE
        self._update_snapshot()
        self._send(self.enc.mav.command_ack_encode(command, result, 0, 0, msg.get_srcSystem(),
                                                   msg.get_srcComponent()))

    def _split_custom(self, custom_mode: int) -> tuple[int, int]:
        if self.flavour is Flavour.PX4:
            return (custom_mode >> 16) & 0xFF, (custom_mode >> 24) & 0xFF
        return custom_mode, 0

    def _set_interval(self, msg_id: int, interval_us: float) -> tuple[int, str]:
        if msg_id not in DEFAULT_RATES:
            return int(mav.MAV_RESULT_DENIED), f"message {msg_id} cannot be streamed"
        if interval_us < 0:
            self.intervals[msg_id] = math.inf
        elif interval_us == 0:  # the default rate: ArduPilot's stock one is "not streamed"
            self.intervals[msg_id] = 1.0 / DEFAULT_RATES[msg_id] if self.flavour is Flavour.PX4 else math.inf
        else:
            self.intervals[msg_id] = max(interval_us * 1e-6, self.dt)
        self.next_due[msg_id] = self.t
        return int(mav.MAV_RESULT_ACCEPTED), ""

    def _on_request_data_stream(self, msg: Any) -> None:
        if self.flavour is not Flavour.ARDUPILOT or not self._for_us(msg):
            return  # PX4 ignores the legacy request
        hz = float(msg.req_message_rate) if msg.start_stop else 0.0
        self._set_group(int(msg.req_stream_id), hz)
        self.log.write("event", self.t, event="request_data_stream", stream=int(msg.req_stream_id), rate_hz=hz)

    def _request_message(self, msg_id: int) -> tuple[int, str]:
        if msg_id == mav.MAVLINK_MSG_ID_AUTOPILOT_VERSION:
            self._send(tm.autopilot_version(self.enc.mav, self.flavour, self.config.sysid))
        elif msg_id == px4.MSG_ID_COMPONENT_METADATA and self.px4 is not None:
            self._send(self.px4.component_metadata())
        elif msg_id in DEFAULT_RATES:
            self._send_stream(msg_id, self._target(), requested=True)
        else:
            return int(mav.MAV_RESULT_UNSUPPORTED), f"message {msg_id} not available"
        return int(mav.MAV_RESULT_ACCEPTED), ""

    def _on_setpoint(self, msg: Any) -> None:
        s = self.vehicle.state
        record: dict[str, Any] = {
            "frame": int(msg.coordinate_frame), "type_mask": int(msg.type_mask),
            "target_system": int(msg.target_system), "target_component": int(msg.target_component),
            "raw_pos": [msg.x, msg.y, msg.z], "raw_vel": [msg.vx, msg.vy, msg.vz],
            "raw_acc": [msg.afx, msg.afy, msg.afz], "yaw": msg.yaw, "yaw_rate": msg.yaw_rate,
            # the sender's clock: gaps in it are the sender's, not this loop's scheduling
            "time_boot_ms": int(msg.time_boot_ms),
        }
        if not self._for_us(msg):
            self.log.write("setpoint", self.t, **record, valid=False, applied=False, reason="not for us")
            return
        if self.flavour is Flavour.ARDUPILOT and self.mode != "GUIDED":
            self.log.write("setpoint", self.t, **record, valid=False, applied=False, reason="not in GUIDED")
            return
        here = (float(s.pos[0]), float(s.pos[1]), float(s.pos[2]))
        d = decode_setpoint(self.flavour, msg, here, s.yaw)
        applied = False
        reason = d.reason
        if d.valid:
            if self.t - self.last_sp > STREAM_GAP_S:
                self.stream_start = self.t
            self.last_sp = self.t
            if self.failsafe_mode is not None and self.armed and self.user_mode == "OFFBOARD":
                # PX4 re-runs the user's mode as soon as it can: one setpoint within COM_OF_LOSS_T.
                self._clear_failsafe("offboard signal regained")
        elif self.flavour is Flavour.PX4 and self.t - self._last_reject_text.get(d.reason, -math.inf) >= 1.0:
            # PX4 reports each rejection, throttled like its mavlink_log.
            self._last_reject_text[d.reason] = self.t
            self._report(mav.MAV_SEVERITY_CRITICAL, f"SET_POSITION_TARGET_LOCAL_NED {d.reason}", None)
        if d.stop:
            # ArduPilot with shaping: "stop" is GUIDED's init, zero velocity from where it is
            # (sitl_mock.ardupilot.stop_target); else a hold at the current position.
            self.follow_target = (self.ap.stop_target(cast("MockAutopilot", self))
                                  if self.flavour is Flavour.ARDUPILOT and self.config.shaping
                                  else Target.hold(s.pos.copy(), s.yaw))
            applied = True
        elif d.setpoint is not None and self.mode == self.modes.follow_mode:
            if self.flavour is Flavour.ARDUPILOT and self.landed and not self.guided_taken_off:
                reason = "landed: takeoff first"
            else:
                sp = d.setpoint
                prev_yaw = self.follow_target.yaw if self.follow_target is not None else s.yaw
                self.follow_target = Target(
                    np.array(sp.pos), np.array(sp.vel), np.array(sp.acc),
                    sp.yaw if math.isfinite(sp.yaw) else (prev_yaw if math.isnan(sp.yaw_rate) else math.nan),
                    sp.yaw_rate,
                )
                applied = True
        elif d.setpoint is not None:
            reason = f"not in {self.modes.follow_mode}"
        tgt = self.follow_target if applied and self.follow_target is not None else None
        self.log.write(
            "setpoint", self.t, **record, valid=d.valid, applied=applied, reason=reason,
            pos=tgt.pos.tolist() if tgt else None, vel=tgt.vel.tolist() if tgt else None,
            acc=tgt.acc.tolist() if tgt else None,
        )

    def _on_param_list(self, msg: Any) -> None:
        if msg.target_system not in (0, self.config.sysid):
            return
        count = len(self.params)
        for i, p in enumerate(self.params.values()):
            self._send(tm.param_value(self.enc.mav, self.flavour, p, count, i))

    def _param_name(self, raw: Any) -> str:
        return (raw.decode(errors="replace") if isinstance(raw, bytes) else str(raw)).rstrip("\x00")

    def _on_param_read(self, msg: Any) -> None:
        if msg.target_system not in (0, self.config.sysid):
            return
        names = list(self.params)
        name = self._param_name(msg.param_id)
        if msg.param_index >= 0:
            name = names[msg.param_index] if msg.param_index < len(names) else ""
        if name in self.params:
            self._send(tm.param_value(self.enc.mav, self.flavour, self.params[name], len(names),
                                      names.index(name)))

    def _on_param_set(self, msg: Any) -> None:
        if msg.target_system not in (0, self.config.sysid):
            return
        name = self._param_name(msg.param_id)
        if name not in self.params:
            self._report(mav.MAV_SEVERITY_WARNING, f"unknown param {name}", None)
            return
        old = self.params[name]
        value = tm.decode_param_value(self.flavour, old.ptype, float(msg.param_value))
        self.params[name] = Param(name, value, old.ptype)
        self.log.write("event", self.t, event="param_set", name=name, value=value)
        names = list(self.params)
        self._send(tm.param_value(self.enc.mav, self.flavour, self.params[name], len(names),
                                  names.index(name)))

    def _on_mission_list(self, msg: Any) -> None:
        if msg.target_system not in (0, self.config.sysid):
            return
        self._send(self.enc.mav.mission_count_encode(msg.get_srcSystem(), msg.get_srcComponent(), 0,
                                                     msg.mission_type))

    def _on_timesync(self, msg: Any) -> None:
        if msg.tc1 == 0:
            now_ns = int((self.t - self.boot_t) * 1e9)
            self._send(self.enc.mav.timesync_encode(now_ns, msg.ts1))


def _int(value: float) -> int:
    """MAVLink float parameter as an integer; NaN (unset) becomes -1."""
    return round(value) if math.isfinite(value) else -1
