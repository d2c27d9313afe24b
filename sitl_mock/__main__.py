"""``python -m sitl_mock``: run a mock PX4 / ArduPilot autopilot."""

from __future__ import annotations

import argparse
import math
import signal
import sys
from types import FrameType

from .faults import parse_faults, parse_seconds
from .server import MockAutopilot, MockConfig
from .signing import read_signing_key
from .transport import PX4_SITL_ENDPOINT
from .vehicle import RESPONSES


def _takeover(text: str) -> tuple[float, str]:
    at, sep, mode = text.partition(":")
    if not sep or not mode:
        raise argparse.ArgumentTypeError(f"--takeover-at: expected SECONDS:MODE, got {text!r}")
    return parse_seconds(at, "takeover-at"), mode


def _triple(text: str) -> tuple[float, float, float]:
    parts = text.split(",")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError(f"--wind: expected N,E,D in m/s, got {text!r}")
    return float(parts[0]), float(parts[1]), float(parts[2])


def _home(text: str) -> tuple[float, float, float]:
    parts = text.split(",")
    try:
        lat, lon, alt = (float(v) for v in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--home: expected LAT,LON,ALT (degrees, degrees, m AMSL), got {text!r}") from None
    if not (-90.0 <= lat <= 90.0 and -180.0 <= lon <= 180.0 and math.isfinite(alt)):
        raise argparse.ArgumentTypeError(f"--home: latitude in [-90, 90], longitude in [-180, 180], got {text!r}")
    return lat, lon, alt


def _param(text: str) -> tuple[str, float]:
    name, sep, value = text.partition("=")
    if not sep:
        raise argparse.ArgumentTypeError(f"--param: expected NAME=VALUE, got {text!r}")
    return name.strip().upper(), float(value)


def _rc(text: str) -> int | None:
    if text.strip().lower() in ("none", "off", "no"):
        return None
    try:
        return int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"--rc-throttle: expected a pwm (e.g. 1000, 1500) or 'none', got {text!r}") from None


def _shift(text: str) -> tuple[float, float]:
    try:
        n, e = (float(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected two metres N,E (e.g. -0.011,0.008), got {text!r}") from None
    return n, e


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(prog="python -m sitl_mock", description=__doc__)
    p.add_argument("--autopilot", choices=["px4", "ardupilot"], default="px4")
    p.add_argument("--endpoint", action="append", dest="endpoints", metavar="KIND:HOST:PORT",
                   help=f"udpin:H:P, udpout:H:P[@BH:BP], tcpin:H:P or tcpout:H:P (dial H:P); repeatable "
                   f"(default {PX4_SITL_ENDPOINT}: PX4 SITL's offboard pair, which the companion's default URL "
                   "meets)")
    p.add_argument("--px4-sitl-ports", action="store_true",
                   help=f"act as PX4 SITL's offboard link: {PX4_SITL_ENDPOINT} (listen on 14580, send to 14540, "
                   "where MAVSDK, MAVROS and the companion's default udpin:127.0.0.1:14540 listen)")
    p.add_argument("--sysid", type=int, default=1)
    p.add_argument("--compid", type=int, default=1)
    p.add_argument("--log", dest="log_path", metavar="FILE.jsonl")
    p.add_argument("--log-rate-hz", type=float, default=None,
                   help="state records per second (default: every simulation step)")
    p.add_argument("--speed", type=float, default=1.0, help="simulated seconds per wall second")
    p.add_argument("--control", metavar="HOST:PORT", help="JSON-lines control socket")
    p.add_argument("--fault", action="append", default=[],
                   help="drop=F, latency=50ms, pause=AT:SECONDS, reboot=AT, reject-arming; repeatable")
    p.add_argument("--takeover-at", action="append", type=_takeover, default=[], metavar="SECONDS:MODE",
                   help="switch mode at this simulated time as a pilot would")
    p.add_argument("--rate-hz", type=float, default=250.0)
    p.add_argument("--home", type=_home, default=None, metavar="LAT,LON,ALT",
                   help="where the mock stands in the world: latitude, longitude (degrees) and ground altitude "
                   "(m AMSL) of its boot point; GPS_GLOBAL_ORIGIN, HOME_POSITION and the global positions follow "
                   "(default 47.397742,8.545594,488, as PX4 SITL; south or west: --home=-33.86,151.21,12); overrides "
                   "--home-lat/--home-lon/--home-alt")
    p.add_argument("--home-lat", type=float, default=47.397742)
    p.add_argument("--home-lon", type=float, default=8.545594)
    p.add_argument("--home-alt", type=float, default=488.0)
    p.add_argument("--seed", type=int, default=None)
    p.add_argument("--wind", type=_triple, default=(0.0, 0.0, 0.0), metavar="N,E,D")
    p.add_argument("--noise", type=float, default=0.0, help="position noise std (m)")
    p.add_argument("--offboard-warmup", type=float, default=1.0, metavar="SECONDS",
                   help="how long a >= 2 Hz setpoint stream must run before OFFBOARD is allowed "
                   "(PX4 docs: 1 s; 0: PX4 code's rule, one setpoint within COM_OF_LOSS_T)")
    p.add_argument("--response", choices=sorted(RESPONSES), default=None,
                   help="vehicle response: px4_sih (PX4's default; ~0.34 s lag as PX4 1.15 SIH), calibrated "
                   "(ArduPilot's default; fitted to ArduCopter SITL, ~60 ms lag) or ideal (follows a full "
                   "feed-forward at once: fast unit tests) or px4_sih_drag (px4_sih with SIH's drag and PX4's "
                   "velocity integral: trails a plan for seconds as PX4 SIH does)")
    p.add_argument("--signing-key", metavar="FILE",
                   help="MAVLink 2 signing: a file holding the 32-byte key (raw, or 64 hex digits); unsigned or "
                   "wrongly signed commands and setpoints are then ignored")
    p.add_argument("--param", action="append", type=_param, default=[], metavar="NAME=VALUE")
    p.add_argument("--ground-z", type=float, default=None, metavar="METRES",
                   help="z (NED) of the ground in the local frame (default: px4 +1.6, i.e. 1.6 m below the "
                   "local origin as on PX4 SITL; ardupilot 0)")
    p.add_argument("--px4-ready-after", type=float, default=None, metavar="SECONDS", dest="px4_ready_s",
                   help="PX4: seconds from boot until arming is allowed, as PX4's estimator settles (default "
                   "36.5, as PX4 1.15 SIH; 0: ready at boot)")
    p.add_argument("--px4-drift", type=float, default=None, metavar="METRES", dest="px4_drift_m",
                   help="PX4: how far the estimate on the ground drifts horizontally before ready, reset at "
                   "ready (default 30; PX4 SIH measured 23-42 m; 0: none)")
    p.add_argument("--px4-statustext", action="store_true",
                   help="PX4: report with STATUSTEXT as PX4 < 1.14 did, instead of EVENT messages")
    p.add_argument("--rc-throttle", type=_rc, default=1000, metavar="PWM|none",
                   help="ArduPilot: the throttle pwm received (default 1000, as SITL with no transmitter: pilot "
                   "modes descend; 1500 mid-stick holds; 'none': no RC ever seen)")
    p.add_argument("--ekf-origin-delay", type=float, default=40.0, metavar="SECONDS",
                   help="ArduPilot: seconds after boot until the EKF origin is set; before it no LOCAL_POSITION_NED, "
                   "GPS_GLOBAL_ORIGIN, HOME_POSITION and no arming in GUIDED (default 40; SITL measured 43)")
    p.add_argument("--position-after-origin", type=float, default=22.0, metavar="SECONDS",
                   help="ArduPilot: seconds from the EKF origin (and home) to the first LOCAL_POSITION_NED "
                   "(default 22: stock ArduCopter 4.6 SITL, measured)")
    p.add_argument("--home-shift-at-arming", type=_shift, default=(-0.011, 0.008), metavar="N,E",
                   help="ArduPilot: metres the ground estimate moves from the origin's home before arming, so home "
                   "moves when it arms (default -0.011,0.008: stock ArduCopter 4.6 SITL, measured; 0,0: home stays)")
    p.add_argument("--spool-up", type=float, default=3.0, metavar="SECONDS",
                   help="ArduPilot: no climb for this long after arming (default 3.0, as measured on SITL)")
    p.add_argument("--no-shaping", dest="shaping", action="store_false",
                   help="do not shape targets with the autopilot's limits (ArduCopter WPNAV_*, PX4 MPC_*)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    if args.home is not None:
        args.home_lat, args.home_lon, args.home_alt = args.home
    try:
        config = MockConfig(
            autopilot=args.autopilot,
            # by default PX4 SITL's offboard pair, which the companion's default URL
            # (udpin:127.0.0.1:14540) meets: a newcomer starting both with no options gets a link
            endpoints=(args.endpoints or []) + ([PX4_SITL_ENDPOINT] if args.px4_sitl_ports else [])
            or [PX4_SITL_ENDPOINT],
            sysid=args.sysid, compid=args.compid, log_path=args.log_path, speed=args.speed,
            control=args.control, faults=parse_faults(args.fault), rate_hz=args.rate_hz,
            log_rate_hz=args.log_rate_hz, home_lat=args.home_lat, home_lon=args.home_lon,
            home_alt=args.home_alt, seed=args.seed, wind=args.wind, noise=args.noise,
            takeovers=args.takeover_at, params=dict(args.param),
            offboard_warmup_s=args.offboard_warmup, vehicle=RESPONSES[args.response] if args.response else None,
            signing_key=read_signing_key(args.signing_key) if args.signing_key else None,
            ground_z=args.ground_z, px4_statustext=args.px4_statustext, px4_ready_s=args.px4_ready_s,
            px4_drift_m=args.px4_drift_m,
            rc_throttle=args.rc_throttle, ekf_origin_delay_s=args.ekf_origin_delay, spool_up_s=args.spool_up,
            position_after_origin_s=args.position_after_origin, home_shift_at_arming=args.home_shift_at_arming,
            shaping=args.shaping,
        )
        mock = MockAutopilot(config)
        mock.bind()
    except (ValueError, OSError) as exc:
        print(f"sitl_mock: {exc}", file=sys.stderr)
        return 2

    def on_signal(signum: int, frame: FrameType | None) -> None:
        mock.request_stop()

    signal.signal(signal.SIGINT, on_signal)
    signal.signal(signal.SIGTERM, on_signal)
    ends = ", ".join(f"{e} -> {a[0]}:{a[1]}" for e, a in zip(config.endpoints, mock.addresses, strict=True))
    print(f"sitl_mock {config.autopilot} sysid {config.sysid} on {ends}", file=sys.stderr, flush=True)
    try:
        mock.run()
    finally:
        mock.stop()
    return 0


if __name__ == "__main__":
    sys.exit(main())
