"""The configuration file's sections: one frozen dataclass per `[table]`, each option with its
default and why it is set so. `companion.config` puts them together (`Config`), checks the
values and loads and writes the TOML; the hand-over's per-autopilot hold profiles are
companion.handover's.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass(frozen=True)
class VehicleConfig:
    id: str = "drone1"
    # MAVLink system id of the autopilot; the companion shares it (same system).
    sysid: int = 1
    autopilot_component: int = 1
    # MAV_COMP_ID_ONBOARD_COMPUTER
    component: int = 191


@dataclass(frozen=True)
class ZenohConfig:
    prefix: str = "bezier"
    mode: str = "peer"
    # Loopback only unless configured: any peer that reaches a listening endpoint may
    # command the vehicle unless Zenoh authenticates it (config_file; docs/security.md).
    # Without config_file the service never connects out to peers it scouts.
    listen: tuple[str, ...] = ("tcp/127.0.0.1:7447",)
    connect: tuple[str, ...] = ()
    multicast_scouting: bool = True
    # Zenoh's shared-memory transport: a peer on the same computer that publishes a message over
    # 3 kB has its 16 MB pool mapped into the companion (main RSS 82 -> 102 MB after big missions
    # sent by a local tool, issue 21), and any local peer could make it map more. Off: local
    # peers' messages are copied over the socket like everyone else's.
    shared_memory: bool = False
    # A full Zenoh JSON5 configuration (TLS, user/password, access control).
    # When set, it is the base and the options above are applied over it only
    # where they differ from their defaults.
    config_file: str = ""


@dataclass(frozen=True)
class MavlinkConfig:
    # udpin:HOST:PORT (we listen; the autopilot sends first: PX4 SITL and PX4's Onboard-mode
    # links send to 14540), udpout:HOST:PORT (we send first), tcp:HOST:PORT (ArduPilot SITL:
    # tcp:127.0.0.1:5760), tcpin:HOST:PORT (we listen; the autopilot dials in: ArduPilot SITL's
    # --serial0 tcpclient:HOST:PORT, a mavlink-router TCP client endpoint; one connection at a
    # time, the next accepted when it ends), serial:/dev/ttyAMA0:921600 (or /dev/ttyAMA0:921600); behind
    # mavlink-router: the UDP endpoint it was given. Loopback by default: on a network
    # interface, anyone on that network could talk to the companion (docs/security.md). The
    # link is bound to the autopilot ([vehicle] sysid/autopilot_component and, on UDP, the
    # address of its first heartbeat); other senders are ignored.
    url: str = "udpin:127.0.0.1:14540"
    # MAVLink 2 signing: a file holding the 32-byte key shared with the autopilot (raw, or 64
    # hex digits); everything we send is then signed. "" = unsigned.
    signing_key_file: str = ""
    # Where PX4's events metadata (fetched over MAVLink FTP, per firmware) is cached; "" =
    # systemd's CacheDirectory ($CACHE_DIRECTORY), else $XDG_CACHE_HOME/bezier-companion
    # (~/.cache/bezier-companion).
    events_cache_dir: str = ""
    # With a signing key: messages from the autopilot must be signed with it too (timestamps
    # per link id as the MAVLink spec says); unsigned ones are ignored and counted. false only
    # for an autopilot that signs nothing it sends.
    require_signed_inbound: bool = True
    heartbeat_hz: float = 1.0
    # No heartbeat from the autopilot for this long means the link is lost.
    link_timeout: float = 1.5
    command_timeout: float = 2.0


@dataclass(frozen=True)
class SetpointConfig:
    rate_hz: float = 50.0
    # "hold": keep the heading measured when the companion takes control;
    # "fixed": always `yaw`; "velocity": face along the horizontal velocity.
    yaw_mode: str = "hold"
    yaw: float = 0.0  # rad, NED heading used in fixed mode
    # Below this speed the along-velocity heading is ill-defined; keep the last one.
    yaw_min_speed: float = 0.3
    # > 0: the setpoint thread (only it: ~50 µs of work a tick) asks for SCHED_FIFO
    # at this priority (needs CAP_SYS_NICE or RLIMIT_RTPRIO; a warning and normal
    # scheduling otherwise). The systemd unit's CPUSchedulingPolicy=fifo does the
    # same without any capability (see companion/rtsched.py and docs/deploy.md).
    realtime_priority: int = 0
    # The setpoint stream from a process of its own (true) or from a thread of the service's
    # (false). A thread needs the service's GIL for every tick, which a loaded computer under
    # normal scheduling does not always give it (companion/sendproc.py).
    process: bool = True
    # Lag compensation: sample each setpoint this far ahead on the verified trajectory (s),
    # so that the vehicle, which lags its setpoints, flies the plan on time. "auto": the lag
    # estimated in flight from telemetry (status `lag_estimate_ms`; companion/lag.py), for
    # both autopilots; a number: that fixed lead; 0: none. Plan changes split after the
    # setpoints already sent (now + lead + [planner] split_ahead).
    lead: float | str = "auto"
    # The most the lead (and the lag estimate) may be (s): PX4 SIH lags ~0.3 s, ArduCopter ~0.06 s.
    lead_max: float = 0.5
    # With lead = "auto": the lead until the estimate has seen enough motion (a few seconds of
    # it): seconds (default ArduCopter's measured lag, 59-82 ms, autopilot-facts.md), or
    # "autopilot": the lag measured on the autopilot found at link-up (companion.lag MEASURED_LAG:
    # ArduCopter 0.06 s, PX4 SIH 0.33 s; ArduCopter's until one is found). Without it the first
    # seconds of every flight lag by the whole response time (0.2-0.25 m at 3-4 m/s on
    # ArduCopter); on PX4 from 0.06 s, ~0.27 s x the speed (0.96 m peak on the e2e resume flight,
    # 0.25 m from 0.33 s). "autopilot" is not the default yet: the PX4 test kits and the demo
    # fly the mock's ArduCopter-like response on the PX4 flavour (issue 26.5), which it would over-lead.
    lead_initial: float | str = 0.06
    # The aim beyond the plan: each setpoint is the jet of p + k F, F the plan's acceleration
    # low-passed with time constant accel_lead_tc (0: as it is), k = accel_lead (s²). A lead puts
    # the vehicle on time; what is left is its response's shape: ArduCopter uses the
    # acceleration feed-forward only in part and its velocity integrator gives back over a
    # second or two what it gathered, so it trails by ~k F (companion.setpoints.sample;
    # docs/autopilot-limits.md). "autopilot": what was measured on the autopilot found at
    # link-up (companion.lag MEASURED_AIM: ArduCopter k 0.09 s², 1.0 s; PX4 none, not
    # measured); 0: the plan's own jet.
    accel_lead: float | str = "autopilot"
    accel_lead_tc: float = 1.0
    # More terms of the aim, horizontal only: [[k s², tc s], ...] (each k F, F the plan's
    # acceleration low-passed with time constant tc), or "autopilot": companion.lag
    # MEASURED_AIM_HORIZONTAL (none yet: PX4 SIH's, companion.lag PX4_SIH_AIM_HORIZONTAL, is for
    # PX4 SIH with lead 0.08; docs/autopilot-limits.md).
    aim_horizontal: tuple[tuple[float, float], ...] | str = "autopilot"
    # The event loop not running for this long (s) is a stall of the companion: the setpoint
    # thread withholds setpoints from then on (it does so too when it itself wakes 0.5 s late).
    # Awake again, the companion holds (setpoints silent under 0.5 s: the autopilot still flies
    # its plan) or releases control and asks the autopilot to hold (FAILSAFE, `start` again).
    loop_stall_limit: float = 1.5


@dataclass(frozen=True)
class BoundsConfig:
    velocity: float = 3.0
    acceleration: float = 3.0
    jerk: float = 10.0
    snap: float = 50.0


@dataclass(frozen=True)
class PlannerConfig:
    method: str = "iterative"  # "iterative" | "global"
    window: int = 6  # jets per QP: planner_core.iterative.DEFAULT_WINDOW (measured)
    vehicle_radius: float = 0.3
    bounds: BoundsConfig = field(default_factory=BoundsConfig)
    # How far ahead of "now" an in-flight replan splits the trajectory: the
    # planning latency budget plus a margin, so the piece flown never changes.
    split_ahead: float = 0.15
    # In flight, how long (s) the search for the fastest durations of a new mission may take
    # before the plan is swapped in: the service sizes the search (its number of candidate
    # plans) from the planning speed it measured, so a busy computer still answers within about
    # this, with a plan that flies a little slower (event `accepted` says so). The default
    # allocation is always planned; a mission loaded on the ground is searched to the end.
    search_time: float = 0.3
    # In flight, a mission without durations first flies its default allocation (one plan: a
    # few ms to ~0.1 s for 1000 waypoints), and the search's faster plan is swapped in from a
    # later split when it is ready (event `improved`); false: the search's plan is awaited.
    anytime: bool = True
    # "process": plan in a separate process (no GIL shared with the setpoint thread; a
    # planner thread preempted while holding the GIL would stall setpoints on a busy
    # computer). "thread": plan in a thread of the service process (less memory).
    executor: str = "process"
    # Planner workers; one keeps planning serialised.
    workers: int = 1
    # Where full replans that race a braking deadline run (never queued behind a mission plan):
    # "thread" of the service (rare and short; no second planner process, ~65 MB less) or a
    # "process" of their own.
    urgent: str = "thread"
    # false: no process of the service loads numba; they plan with the compiled pass's
    # ahead-of-time build (`make setup` builds it: <1 MB, the same plans), or on the numpy path
    # where it is not built (~10x slower a window step; said at start-up). true: planner
    # processes may also load numba's JIT build when the AOT one is missing (~105 MB more each,
    # benchmarks/footprint.py). The service process never loads numba.
    compiled: bool = False
    # Durations of a mission that gives none: "fastest" (planner_core.plan_mission's fastest
    # allocation within the reserve below) or "default" (planner_core.allocate_times: the 3-piece
    # certificate's rest-to-rest leg takes 2.64 L / v; ~1.5x the fastest flight time).
    timing: str = "fastest"
    # Share of every bound a mission's allocated plan leaves unused (planned within (1 - reserve) x
    # the bounds; replans are checked against the full bounds): what a pop-up's swerve or a stop
    # has left. At 0 a plan flies at the bounds, and a pop-up obstacle near the path more often
    # ends in a verified stop and a hold than in a swerve (docs: README, "Timing").
    reserve: float = 0.2
    # How far the flown track may stray from the plan (m): obstacles (and the map box) are
    # inflated by vehicle_radius + tracking_allowance, and a tracking error above it for
    # 3 samples in a row brakes to a stop (it replaces [safety] max_tracking_error). Compared
    # in flight with the tracking measured (event `tracking_margin` when the RMS or max nears
    # it). "autopilot" (the default): the autopilot's own (TRACKING_ALLOWANCES: PX4 1.0 m, its
    # estimate strays ~0.4 m from a held setpoint; ArduPilot 0.4 m; ArduPilot's before the
    # autopilot is known). 0: neither the inflation nor the brake (planning tests and benches
    # only, not flight).
    tracking_allowance: float | str = "autopilot"
    # Fault injection for tests and drills: hold back the result of the full-replan fallback
    # (after a failed local replan) this many seconds, as on an overloaded computer. The
    # braking deadline must then stop the vehicle. 0 in flight.
    fallback_delay: float = 0.0


# `[planner] tracking_allowance = "autopilot"`: the allowance per autopilot (m), from flights on
# the simulators with stock parameters (docs/autopilot-limits.md). PX4 SIH (9ececfdd, 2026-12-03):
# at 0.40 m missions braked themselves 2.4-4.6 s after their start (its estimate went 0.41 m off
# a held setpoint); at 1.0 m they flew, tracking RMS 0.35-0.36 m, max 0.80 m (a 15 m square).
# ArduCopter 4.6 SITL (issue 20): tracking RMS 0.14-0.21 m in the paper's scenarios, within 0.40 m.
TRACKING_ALLOWANCES = {"px4": 1.0, "ardupilot": 0.4}


def tracking_allowance(planner: PlannerConfig, autopilot: str | None) -> tuple[float, str]:
    """(the tracking allowance in use, where it comes from): `[planner] tracking_allowance` when
    set to a number, else the autopilot's (ArduPilot's while the autopilot is not known)."""
    if not isinstance(planner.tracking_allowance, str):
        return float(planner.tracking_allowance), "[planner] tracking_allowance"
    ap = "px4" if autopilot == "px4" else "ardupilot"
    return TRACKING_ALLOWANCES[ap], f"{'PX4' if ap == 'px4' else 'ArduPilot'}'s default" + (
        "" if autopilot is not None else " (the autopilot not yet known)")


@dataclass(frozen=True)
class GeofenceConfig:
    # NED box; z is down, so the ceiling is the most negative z.
    min: tuple[float, float, float] = (-100.0, -100.0, -50.0)
    max: tuple[float, float, float] = (100.0, 100.0, 0.5)
    # "home": the box is relative to HOME_POSITION once the autopilot reports it (the local
    # frame until then), so its floor follows the ground (PX4's local z on the ground is
    # often +1.5 m); "local": the box is in the autopilot's local frame.
    origin: str = "home"


@dataclass(frozen=True)
class LimitsConfig:
    # What one inbound message may hold. Each refusal names the limit it hit.
    # A larger payload is refused from its size alone (it is never read whole).
    max_message_bytes: int = 1048576
    # Waypoints of one mission (or of one `append` change).
    max_waypoints: int = 5000
    # Obstacles in one message (a mission's own, or one `obstacles` add).
    max_obstacles: int = 1000
    # Vertices of one obstacle given as `vertices` (its hull is qhull's: O(n log n)).
    max_obstacle_vertices: int = 1000
    # Planes of one obstacle (`A` rows, or its hull's faces): vertex enumeration is
    # O(planes^3), ~4 ms at 32 on this 2-core machine, and it runs again for every corridor build.
    max_obstacle_planes: int = 32
    # An obstacle's extent (m, along any axis) and its thinnest width (m): huge or flat
    # obstacles are refused.
    max_obstacle_extent: float = 1000.0
    min_obstacle_width: float = 0.001
    # Every number's magnitude (coordinates, offsets, durations, bounds).
    max_number: float = 100000.0
    # Characters of one number literal (refused before it is converted: Python's int()
    # refuses 4300 digits, and long literals cost time), of one string, and nesting depth.
    max_number_chars: int = 32
    max_string_chars: int = 256
    max_depth: int = 12
    # What the service holds at once: obstacles from the `obstacles` key, mission messages
    # being checked or planned (waiting included), inbound messages queued for decoding.
    max_obstacles_held: int = 256
    max_pending_missions: int = 4
    max_queued_messages: int = 256
    # Messages of one kind (mission, obstacles, change, command) taken per second, and at once:
    # more is refused on arrival, before it costs the event loop anything, and said once a
    # second with the count (a burst of 5,000 obstacle updates stalled the loop 0.6 s).
    inbound_rate: float = 50.0
    inbound_burst: int = 100
    # Seconds one message's obstacles may take to check (hulls, vertices; in the decode
    # thread for messages over 4 kB): past it the message is refused, naming this limit.
    decode_deadline: float = 0.5
    # Seconds one segment of a mission may last (`durations`, `times`, a `duration` change):
    # shorter than min_segment_duration (the planner's own floor: planner_core.timing's
    # DEFAULT_MIN_DURATION) leaves its QP ill-conditioned; longer than max_segment_duration is
    # longer than any flight (and a leg that starts moving would overshoot the map by km).
    min_segment_duration: float = 0.05
    max_segment_duration: float = 3600.0


@dataclass(frozen=True)
class AutopilotLimitsConfig:
    # Read the autopilot's own limits on the setpoints it is streamed (ArduPilot WPNAV_* and
    # PSC_JERK_*, PX4 MPC_*: docs/autopilot-limits.md) at link-up and after a reconnect, and
    # plan within them: the bounds flown are the configured ones (or a mission's own) clipped
    # to limit x headroom. false: plan with the configured bounds only.
    read: bool = True
    # Share of each limit plans may use (the rest is the autopilot's own margin).
    headroom: float = 0.9
    # Seconds to wait for the parameters each try, and how many times to ask again.
    timeout: float = 1.0
    retries: int = 2


@dataclass(frozen=True)
class SafetyConfig:
    auto_arm: bool = False
    takeoff_altitude: float = 2.0
    # A mission's first waypoint or takeoff within this distance counts as reached.
    arrival_tolerance: float = 0.2
    # Takeoff is complete within `arrival_tolerance` of its altitude AND below this speed (m/s).
    rest_speed: float = 0.2
    # The tracking error (m) at which the companion brakes; 0: [planner] tracking_allowance, the
    # margin obstacles are inflated by (the certificate then covers every track flown). Larger
    # only where the obstacles' geometry is fixed by something else (a test rig, a demo) and the
    # vehicle is known to stray further: the track is then outside what was certified.
    tracking_brake: float = 0.0
    # On SIGINT/SIGTERM in flight (or an internal failure the service cannot recover from):
    # brake to a verified stop, then hand over to the autopilot's own "hold" (an autonomous
    # hold that needs no pilot: PX4 AUTO.LOITER; ArduPilot GUIDED holding a position target at
    # the stop point, or BRAKE when setpoints can no longer be sent: docs/handover.md), "land"
    # or "rtl", confirm it by watching the vehicle, and exit (at most `exit_timeout` s in
    # all). Keep it below systemd's TimeoutStopSec.
    on_exit: str = "hold"
    exit_timeout: float = 0.0
    # A pilot mode to hand over to instead of the autonomous hold (ArduPilot LOITER, ALT_HOLD,
    # POSHOLD; PX4 POSCTL, ALTCTL): used only when a pilot is known present (`pilot_present`,
    # or RC_CHANNELS from a live transmitter with the throttle stick centred); otherwise the
    # autonomous hold, and an event says why. With no pilot input, ArduCopter's pilot modes
    # descend (throttle at minimum: -PILOT_SPEED_DN).
    exit_pilot_mode: str = ""
    pilot_present: bool = False
    # The hand-over is confirmed by watching the vehicle, not only its mode: for `hold_confirm`
    # s its altitude stays within `hold_altitude_tolerance` m of where the hold began and its
    # speed below `hold_speed_tolerance` m/s once `hold_settle` s have passed since the
    # verified stop's end (the autopilot's own braking); otherwise it is reported as failed
    # (exit 1). 0 (the default) for any of these and `exit_timeout`: the autopilot's profile
    # (companion.handover.HOLD_PROFILES, docs/handover.md: PX4 and ArduPilot differ); a value set here overrides it.
    hold_confirm: float = 0.0
    hold_altitude_tolerance: float = 0.0
    hold_speed_tolerance: float = 0.0
    hold_settle: float = 0.0
    # The speed (m/s) the braking before the hand-over waits for, at most `hold_settle` s past
    # the verified stop's end; 0: the autopilot's profile (PX4 0.7 m/s: its estimate strays in
    # OFFBOARD and is rarely under 0.2 m/s; ArduPilot `rest_speed` above).
    hold_rest_speed: float = 0.0


@dataclass(frozen=True)
class RecordingConfig:
    # A directory: one MCAP file per run of the service (docs/recording.md); "" = no recording.
    # Not set in the file: $BEZIER_COMPANION_RECORDING if set (the systemd unit sets it to the
    # unit's state directory), else no recording.
    path: str = ""
    # A file is closed and a new one started past this size (bytes) ...
    max_bytes: int = 134217728
    # ... and the oldest files in `path` are removed while all of them hold more than this.
    keep_bytes: int = 1073741824
    # Records waiting for the writer thread; past it, records are dropped and counted
    # (setpoints have a queue of their own of this size too: a burst of other traffic never
    # drops one).
    queue: int = 4096


@dataclass(frozen=True)
class LiveConfig:
    # "HOST:PORT" of a Foxglove WebSocket server with the recording's channels; "" = off.
    # Loopback unless you mean it: anyone who reaches it sees the flight (read-only).
    foxglove: str = ""


@dataclass(frozen=True)
class FleetConfig:
    # The fleet frame: NED (and ENU) metres about this point, [lat_deg, lon_deg, alt_m AMSL]; [] = none
    # (a single vehicle). Messages may then say `"origin": "fleet"`; status `fleet` says where the
    # autopilot's local frame sits in it (docs/fleet.md).
    origin: tuple[float, ...] = ()
    # A vehicle without GPS: where its local NED origin is in the fleet frame (NED, m), e.g. measured
    # on the ground; [] = from the autopilot's GPS_GLOBAL_ORIGIN (or HOME_POSITION).
    offset_ned: tuple[float, ...] = ()
    # How far apart (s) the vehicles' system clocks may be (NTP, chrony, PTP): times between
    # vehicles are absolute, and this much is paid for in the separation between their plans.
    clock_tolerance: float = 0.05
    # Separation between vehicles (issue 24.3, docs/fleet.md), with [fleet] origin set: every plan
    # keeps this distance (m, centre to centre; plus clock_tolerance x the two bound speeds) from
    # every other vehicle's committed trajectory; 0 = no deconfliction (the frame only).
    separation: float = 3.0
    # The bound on a message's delay between two vehicles through the router (s): a new plan is
    # proposed, then committed (flown) 2 x max_delay later if no conflicting plan won meanwhile.
    max_delay: float = 0.1
    # The tie-break between two vehicles planning at once: the higher priority wins, then the
    # smaller vehicle id.
    priority: int = 0

