"""The configuration's frozen dataclasses (buses, drives, drive system, recorder) and their
fixed values; what the rest of the stack reads. No parsing here (:mod:`can_config.config`).

Owner: none; values only (frozen dataclasses).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from can_config.errors import ConfigError
from can_config.keys import REQUIRED, key

DATA_DIR = Path(__file__).resolve().parent / "data"
GENERIC_EDS = DATA_DIR / "generic_cia402.eds"
DEFAULT_CONFIG = DATA_DIR / "default.yaml"
#: The socketcand protocol's usual TCP port: the simulator's default and the driver's when a
#: config's socketcand bus names no port (the driver and the simulator meet only on the bus).
SOCKETCAND_PORT = 29536
#: ``on_host_loss`` -> the CiA 402 abort connection option code (0x6007) written at boot.
ON_HOST_LOSS = {"quick_stop": 3, "disable": 2, "fault": 1}

#: Motor revolutions per joint revolution: below 0.001 a 4096-count encoder gives under 5
#: counts per joint revolution, and a move rounds to no motion at all.
GEAR_RATIO_MIN = 0.001
GEAR_RATIO_MAX = 1e6


@dataclass(frozen=True)
class BusConfig:
    """One CAN bus, opened as ``can.Bus(interface=..., channel=..., bitrate=..., **kwargs)``."""

    name: str = key("name", help="the bus's name, used by drives' `bus` and in logs")
    interface: str = key(
        "str",
        help="python-can interface: `socketcan` (the rover, vcan), `socketcand` (the simulator), `pcan`, ...")
    channel: str = key("str", help="python-can channel: `can0`, `vcan0`, `PCAN_USBBUS1`, ...")
    bitrate: int = key("int", 1_000_000, 10_000, 8_000_000, unit="bit/s",
                       help="the bus bitrate (bus load planning; set on the interface by `can-up`)")
    restart_ms: int = key("int", 100, 0, 60_000, unit="ms",
                          help="a SocketCAN controller's automatic restart after a bus-off, set on the interface by"
                               " `can-up` (0: it stays off until restarted by hand)")
    txqueuelen: int = key("int", 1000, 10, 100_000,
                          help="a SocketCAN interface's transmit queue in frames, set by `can-up` (a controller's"
                               " default of 10 fills with one burst)")
    kwargs: Mapping[str, Any] = key(
        "map", {},
        help="more python-can arguments, e.g. `{host: 127.0.0.1, port: 29536}` for socketcand")
    sync_period_s: float = key("float", 10.0, 1.0, 1000.0, yaml="sync_period_ms", scale=1000, unit="ms",
                               help="SYNC period: the rate of every synchronous PDO")
    host_node_id: int = key("int", 127, 1, 127, help="the driver's own NMT id; no drive on the bus may use it")
    host_heartbeat_s: float = key("float", 50.0, 10.0, 1000.0, yaml="host_heartbeat_ms", scale=1000, unit="ms",
                                  help="period of the driver's heartbeat, which the drives watch")
    connect_timeout_s: float = key("float", 10_000.0, 0.0, 600_000.0, yaml="connect_timeout_ms", scale=1000, unit="ms",
                                   help="how long the driver waits for a bus server that is not there yet")
    #: auto: the bus's own timer sends the SYNC (the kernel's on SocketCAN, the daemon's on
    #: socketcand); thread: a thread of the driver process does
    sync_timer: str = key(
        "str", "auto", choices=("auto", "thread"),
        help="`auto`: the daemon's or kernel's timer sends the SYNC; `thread`: a thread of the driver")

    def bus_kwargs(self) -> dict[str, Any]:
        """Keyword arguments for :func:`can.Bus`."""
        args: dict[str, Any] = {"interface": self.interface, "channel": self.channel}
        if self.interface not in ("socketcand", "rovercan"):
            args["bitrate"] = self.bitrate
        if self.interface == "socketcand":
            # latency first: without TCP_NODELAY/QUICKACK, Nagle and delayed ACKs hold small
            # frames 20-40 ms; a config says tcp_tune: false to turn it off
            args["tcp_tune"] = True
        args.update(self.kwargs)
        return args


@dataclass(frozen=True)
class IdentityConfig:
    """Expected 0x1018 identity; ``None`` fields are not checked."""

    vendor_id: int | None = key("int", None, 0, 4_294_967_295, help="0x1018:1, compared at boot")
    product_code: int | None = key("int", None, 0, 4_294_967_295, help="0x1018:2")
    revision: int | None = key("int", None, 0, 4_294_967_295, help="0x1018:3")


@dataclass(frozen=True)
class SdoSetting:
    """One vendor parameter written at boot (``sdo:`` list of a drive), in the list's order."""

    index: int = key("int", REQUIRED, 4096, 65_535, help="object index")
    sub: int = key("int", 0, 0, 255, help="sub-index")
    value: int | float = key("number", attr_default=0, help="the value written")
    check: bool = key("bool", True, help="read it back after writing")
    size: int | None = key("opt_int", None, 1, 8, unit="bytes",
                           help="the object's width where the EDS does not list it")


@dataclass(frozen=True)
class SimModelConfig:
    """The simulator's motor and load model of one drive (``sim:`` of a drive; the driver
    ignores it). Motor side of the gear; the defaults look like one wheel of a ~60 kg
    six-wheeled rover behind a 50:1 gear. Gains left out follow from the inertia and the
    velocity loop's bandwidth."""

    inertia_kg_m2: float = key("float", 0.0001, 0.0, 100.0, low_open=True, unit="kg m^2",
                               help="rotor plus load inertia")
    viscous_nm_s_rad: float = key("float", 2e-05, 0.0, 100.0, unit="Nm s/rad", help="viscous friction")
    coulomb_nm: float = key("float", 0.03, 0.0, 10_000.0, unit="Nm", help="Coulomb friction")
    load_nm: float = key("float", 0.0, -10_000.0, 10_000.0, unit="Nm", help="a constant load torque")
    torque_lag_s: float = key("float", 1.0, 0.0, 100.0, yaml="torque_lag_ms", scale=1000, unit="ms",
                              help="current loop time constant")
    bandwidth_hz: float = key("float", 50.0, 0.0, 1000.0, low_open=True, unit="Hz",
                              help="velocity loop bandwidth (gains derived from it)")
    position_kp: float | None = key("opt_float", None, 0.0, 10_000.0, unit="1/s",
                                    help="position gain (default: from the bandwidth)")
    velocity_kp: float | None = key("opt_float", None, 0.0, 10_000.0, unit="Nm s/rad",
                                    help="velocity gain (default: from the bandwidth)")
    velocity_ki: float | None = key("opt_float", None, 0.0, 1_000_000.0, unit="Nm/rad",
                                    help="velocity integral gain (default: from the bandwidth)")
    velocity_ff: float = key("float", 1.0, 0.0, 2.0, help="velocity feed-forward")
    sync_answer_delay_s: float = key(
        "float", 0.0, 0.0, 1000.0, yaml="sync_answer_delay_ms", scale=1000, unit="ms",
        help="its synchronous TPDOs leave this long after the SYNC, with the values of the SYNC's moment"
             " (a slow drive, a busy bus); its frames stay in order")
    sync_answer_jitter_s: float = key(
        "float", 0.0, 0.0, 1000.0, yaml="sync_answer_jitter_ms", scale=1000, unit="ms",
        help="plus a random 0 to this much each SYNC, the drive's frames still in order")


@dataclass(frozen=True)
class DriveConfig:
    """One CiA 402 drive and the joint it moves."""

    name: str = key("name", help="the joint's name (topics, services, /joint_states)")
    node_id: int = key("int", REQUIRED, 1, 127, help="CANopen node id of the drive")
    bus: str = key("str", None, required=True, help="the bus it is on (default: the only bus)")
    eds: Path = key("path", "generic", required=True,
                    help="`generic` (the project's CiA 402 EDS) or the vendor's EDS, relative to the config")
    namespace: str = key("namespace", "", help="ROS namespace of the joint's topics")
    counts_per_rev: int | None = key(
        "int", None, 1, 2_147_483_647, unit="counts",
        help="position resolution per motor turn; read from the drive's 0x608F where it has one")
    gear_ratio: float = key("float", 1.0, GEAR_RATIO_MIN, GEAR_RATIO_MAX, help="motor turns per joint turn")
    rated_torque_nm: float = key(
        "float", 1.0, 0.0, 100_000.0, low_open=True, unit="Nm",
        help="the motor's rated torque (0x6076 where the drive has it): the unit of torque objects")
    max_torque_nm: float | None = key("opt_float", None, 0.0, 1_000_000.0, low_open=True, unit="Nm",
                                      help="torque command limit at the joint (default: rated torque x gear ratio)")
    joint: str = key("str", "continuous", choices=("continuous", "limited"),
                     help="`continuous` (a wheel) or `limited` (needs `min_deg`/`max_deg`)")
    min_deg: float | None = key("opt_float", None, -10_000_000.0, 10_000_000.0, unit="deg",
                                help="lower position limit of a limited joint (also written to the drive, 0x607D)")
    max_deg: float | None = key("opt_float", None, -10_000_000.0, 10_000_000.0, unit="deg",
                                help="upper position limit of a limited joint")
    max_velocity_deg_s: float = key("float", 360.0, 0.0, 1_000_000.0, low_open=True, unit="deg/s",
                                    help="velocity command limit, every path (API, CLI, ROS)")
    profile_velocity_deg_s: float = key("float", 90.0, 0.0, 1_000_000.0, low_open=True, unit="deg/s",
                                        help="profile position speed (0x6081)")
    profile_acceleration_deg_s2: float = key("float", 360.0, 0.0, 10_000_000.0, low_open=True, unit="deg/s^2",
                                             help="profile acceleration and deceleration (0x6083/0x6084)")
    heartbeat_period_s: float = key("float", 100.0, 10.0, 10_000.0, yaml="heartbeat_period_ms", scale=1000, unit="ms",
                                    help="the drive's heartbeat period (0x1017), or the guard time when node-guarded")
    heartbeat_timeout_s: float = key("float", 350.0, 20.0, 60_000.0, yaml="heartbeat_timeout_ms", scale=1000, unit="ms",
                                     help="no heartbeat (or guard answer) for this long: the drive is lost")
    watchdog_s: float = key("float", 500.0, 10.0, 60_000.0, yaml="watchdog_ms", scale=1000, unit="ms",
                            help="no velocity/torque command for this long: the driver stops the joint")
    arm_on_start: bool = key("bool", False, help="enable the drive when the driver starts (off: safe by default)")
    restore_enable_after_reboot: bool = key("bool", False,
                                            help="enable again after the drive rebooted by itself (off by default)")
    homing_method: int = key("int", 35, -128, 127, help="CiA 402 homing method (0x6098)")
    homing_speed_deg_s: float = key("float", 30.0, 0.0, 1_000_000.0, low_open=True, unit="deg/s",
                                    help="homing speed (0x6099)")
    homing_timeout_s: float = key("float", 10.0, 0.1, 600.0, unit="s", help="homing gives up after this long and quick-stops the drive")
    identity: IdentityConfig = key("map", {}, nested=IdentityConfig,
                                   help="expected 0x1018 (`vendor_id`, `product_code`, `revision`); default: the EDS's")
    invert: bool = key("bool", False, help="the joint turns the other way than the motor (a mirrored wheel)")
    offset_deg: float = key("float", 0.0, -1_000_000.0, 1_000_000.0, unit="deg",
                            help="the joint angle at drive position 0")
    quick_stop_deceleration_deg_s2: float | None = key(
        "opt_float", None, 0.0, 10_000_000.0, low_open=True, unit="deg/s^2",
        help="quick-stop deceleration (0x6085; default 4x the profile's)")
    host_timeout_s: float | None = key(
        "opt_float", None, 20.0, 65_535.0, yaml="host_timeout_ms", scale=1000, unit="ms",
        help="the drive stops itself when the host is silent this long (default 3x the host heartbeat)")
    on_host_loss: str = key("str", "quick_stop", choices=tuple(ON_HOST_LOSS),
                            help="what the drive does then (0x6007): `quick_stop`, `disable` or `fault`")
    allow_no_host_watch: bool = key(
        "bool", False,
        help="arm a drive that cannot watch the host (loud warning): NOTHING stops it if the host dies")
    #: how the drive watches the host: heartbeat consumer (0x1016), node guarding (0x100C/0x100D,
    #: remote frames: kernel buses only), or auto (0x1016 where the drive has it, else guarding)
    host_watch: str = key(
        "str", "auto", choices=("auto", "heartbeat", "guarding"),
        help="`auto` (heartbeat consumer where the drive has 0x1016, else node guarding), `heartbeat`, `guarding`")
    #: 20: a starved non-real-time host sees a whole bus's TPDOs 50-90 ms late now and then; late
    #: data refuses set-points and takes a wheel out, so the bound is past such a pause
    stale_after_syncs: int = key("int", 20, 2, 1000, unit="SYNC periods",
                                 help="one of the drive's TPDOs sent every SYNC (its position's, its statusword's)"
                                      " not heard for this many SYNC periods: the drive's data are late (reported"
                                      " stale; set-points that would move it are refused; the verdict names a TPDO"
                                      " missing while the others come); one lost frame ages the data by a period, so"
                                      " 2 or 3 tolerate no lost frame")
    frame_loss_window_syncs: int = key("int", 500, 20, 1_000_000, unit="SYNC periods",
                                       help="frame loss is measured over this many SYNC periods (TPDOs expected per"
                                            " SYNC against received; heartbeats due, one fewer than the window's"
                                            " whole heartbeat periods, against received)")
    frame_loss_warn_percent: float = key("float", 2.0, 0.0, 100.0, low_open=True, unit="%",
                                         help="more of the drive's TPDOs or heartbeats lost than this over the window:"
                                              " WARN in /diagnostics")
    sdo_timeout_s: float = key("float", 500.0, 10.0, 10_000.0, yaml="sdo_timeout_ms", scale=1000, unit="ms",
                               help="one SDO answer (a whole read: 4x this at most)")
    boot_timeout_s: float = key("float", 2000.0, 100.0, 60_000.0, yaml="boot_timeout_ms", scale=1000, unit="ms",
                                help="from NMT reset to the drive's boot-up")
    sdo: tuple[SdoSetting, ...] = key("list", [], nested=SdoSetting,
                                      help="vendor parameters written at boot, in order (table below)")
    position_mode: str = key("str", "profile", choices=("profile", "cyclic"),
                             help="how `degree_cmd` and /joint_commands positions are sent: `profile` (PP, the set-point"
                                  " handshake: any target within the limits) or `cyclic` (a stream: CSP, or IP where the"
                                  " drive lists no CSP; each set-point within max_velocity_deg_s over two SYNC periods of"
                                  " the last)")
    velocity_mode: str = key("str", "profile", choices=("profile", "cyclic"),
                             help="how /joint_commands velocities are sent: `profile` (PV) or `cyclic` (CSV)")
    torque_mode: str = key("str", "profile", choices=("profile", "cyclic"),
                           help="how efforts are sent: `profile` (PT) or `cyclic` (CST)")
    sim: SimModelConfig = key("map", {}, nested=SimModelConfig,
                              help="the simulator's model of this drive (table below)")

    @property
    def quick_stop_decel_deg_s2(self) -> float:
        return self.quick_stop_deceleration_deg_s2 or 4.0 * self.profile_acceleration_deg_s2

    @property
    def counts_per_deg(self) -> float:
        """Encoder counts per degree of joint motion (motor counts x gear ratio / 360), from the
        config alone (the driver refines it from the drive's own objects at boot)."""
        return (self.counts_per_rev or 4096) * self.gear_ratio / 360.0

    @property
    def is_continuous(self) -> bool:
        return self.joint == "continuous"

    @property
    def ros_prefix(self) -> str:
        """Where the joint's topics and services live: ``namespace/name``, or ``name``."""
        return f"{self.namespace.rstrip('/')}/{self.name}" if self.namespace else self.name


@dataclass(frozen=True)
class DriveSystemConfig:
    """The rover's skid-steer drive system (optional)."""

    left: tuple[str, ...] = key("list_names", help="the drives of the left side")
    right: tuple[str, ...] = key("list_names", help="the drives of the right side")
    track_width_m: float = key("float", 0.6, 0.0, 100.0, low_open=True, unit="m",
                               help="distance between the left and right wheels")
    wheel_radius_m: float = key("float", 0.1, 0.0, 10.0, low_open=True, unit="m", help="wheel radius")
    cmd_timeout_s: float = key("float", 500.0, 10.0, 60_000.0, yaml="cmd_timeout_ms", scale=1000, unit="ms",
                               help="no /cmd_vel for this long: the wheels ramp down and stop")
    max_accel_m_s2: float = key("float", 1.0, 0.0, 100.0, low_open=True, unit="m/s^2",
                                help="acceleration limit of the body and every wheel")
    max_speed_m_s: float = key("float", 1.0, 0.0, 100.0, low_open=True, unit="m/s",
                               help="body speed and every wheel's rim speed")
    max_angular_rad_s: float = key("float", 2.0, 0.0, 100.0, low_open=True, unit="rad/s",
                                   help="turn rate; a faster /cmd_vel is scaled down as a whole")
    on_wheel_loss: str = key("str", "stop", choices=("stop", "continue"),
                             help="a wheel lost, stale or faulted while driving: `stop` every wheel, or `continue` on"
                                  " the others (that wheel told to stop and left out, the body speed cut to the share"
                                  " of wheels left on the weaker side; a side with none left stops all)")
    pose_covariance_diagonal: tuple[float, ...] = key(
        "variances", (0.001, 0.001, 1.0e6, 1.0e6, 1.0e6, 0.01),
        help="/odom pose variances x, y, z, roll, pitch, yaw (m^2, rad^2), each over 0; z, roll and pitch are not"
             " measured (large). While no trusted wheel is left on a side every entry is 1e6")
    twist_covariance_diagonal: tuple[float, ...] = key(
        "variances", (0.001, 0.001, 1.0e6, 1.0e6, 1.0e6, 0.01),
        help="/odom twist variances vx, vy, vz, wx, wy, wz ((m/s)^2, (rad/s)^2), each over 0")




#: The trajectory group a config without ``trajectory_groups`` gets: every limited joint (the arm's),
#: named as MoveIt's controller config expects (``/arm_controller/follow_joint_trajectory``).
DEFAULT_TRAJECTORY_GROUP = "arm_controller"


@dataclass(frozen=True)
class TrajectoryGroupConfig:
    """A group of joints that follows FollowJointTrajectory goals on its bus's SYNC clock (``trajectory_groups:``)."""

    name: str = key("name", help="the group's name: its action is `/<name>/follow_joint_trajectory` (MoveIt's"
                                 " controller name)")
    joints: tuple[str, ...] = key("list_names", help="its joints: limited joints (`joint: limited`) on one bus, each"
                                                      " in one group at most")
    path_tolerance_deg: float = key("float", 5.0, 0.0, 360.0, unit="deg",
                                    help="a joint further than this from the trajectory while it runs aborts the goal"
                                         " (PATH_TOLERANCE_VIOLATED); 0: not checked. A goal's own tolerance wins")
    goal_tolerance_deg: float = key("float", 0.2, 0.0, 360.0, unit="deg",
                                    help="each joint within this of the last point, or the goal aborts"
                                         " (GOAL_TOLERANCE_VIOLATED); 0: not checked. A goal's own tolerance wins")
    goal_time_tolerance_s: float = key("float", 1000.0, 0.0, 60_000.0, yaml="goal_time_tolerance_ms", scale=1000,
                                       unit="ms", help="how long after the trajectory's end the joints may take to get"
                                                       " within the goal tolerance (a goal's own value wins); 0: no"
                                                       " bound, the goal waits until they are (as"
                                                       " joint_trajectory_controller's goal_time 0)")
    start_tolerance_deg: float = key("float", 2.0, 0.0, 360.0, low_open=True, unit="deg",
                                     help="a trajectory whose first point (at time 0) is further than this from both a"
                                          " joint's set-point and its measured position is rejected: nothing moves")
    stop_deceleration_deg_s2: float = key("float", 360.0, 0.0, 10_000_000.0, low_open=True, unit="deg/s^2",
                                          help="a cancelled or failed goal's joints ramp down at this, then hold")
    feedback_rate_hz: float = key("float", 20.0, 1.0, 100.0, unit="Hz", help="the action's feedback rate")
    stopped_velocity_tolerance_deg_s: float = key(
        "float", 0.573, 0.0, 100_000.0, unit="deg/s",
        help="at the goal each joint slower than this, or it is not there yet (joint_trajectory_controller's"
             " constraints.stopped_velocity_tolerance, 0.01 rad/s); 0: not checked. A goal's own velocity"
             " tolerance wins")
    allow_partial_joints_goal: bool = key("bool", False, help="accept a goal naming some of the group's joints (the"
                                                              " others hold); false: a goal must name them all, as"
                                                              " joint_trajectory_controller's default")
    allow_nonzero_velocity_at_trajectory_end: bool = key(
        "bool", False, help="accept a trajectory whose last point has a velocity (the joints then stop dead at its end:"
                            " one SYNC from that velocity to rest); false: such a goal is rejected (INVALID_GOAL), as"
                            " joint_trajectory_controller's default")


@dataclass(frozen=True)
class RecorderConfig:
    """The driver's flight recorder (``recorder:``): the last ``seconds`` of frames and drive
    states, written on each incident with what follows it for ``after_s``."""

    enabled: bool = key("bool", True, help="keep the ring and write incidents")
    dir: Path | None = key(
        "str", None,
        help="where incidents go (default `$ROVERCAN_INCIDENT_DIR`, else `~/.local/state/rovercan/incidents`)")
    seconds: float = key("float", 10.0, 1.0, 600.0, unit="s",
                         help="the ring: frames and states kept before an incident (each bus's ring of frames is allocated at"
                         " start: 22 bytes a frame at the bus's full rate, about 0.2 MB a second per Mbit/s)")
    after_s: float = key("float", 1.0, 0.0, 60.0, unit="s", help="kept after the incident")
    max_mb: float = key("float", 200.0, 1.0, 1_000_000.0, unit="MB",
                        help="the directory's cap; the oldest incidents go first")
    plot: bool = key("bool", True, help="draw a PNG of each incident (needs matplotlib)")

    @property
    def directory(self) -> Path:
        if self.dir is not None:
            return self.dir
        env = os.environ.get("ROVERCAN_INCIDENT_DIR")
        return Path(env) if env else Path.home() / ".local" / "state" / "rovercan" / "incidents"


@dataclass(frozen=True)
class RoverConfig:
    """A whole configuration: buses, drives and, optionally, the drive system."""

    buses: tuple[BusConfig, ...]
    drives: tuple[DriveConfig, ...]
    drive_system: DriveSystemConfig | None = None
    source: Path | None = None
    recorder: RecorderConfig = field(default_factory=RecorderConfig)
    trajectory_groups: tuple[TrajectoryGroupConfig, ...] = ()

    def bus(self, name: str) -> BusConfig:
        for bus in self.buses:
            if bus.name == name:
                return bus
        raise ConfigError(f"no bus named {name!r}; configured buses: {[b.name for b in self.buses]}")

    def drive(self, name: str) -> DriveConfig:
        for drive in self.drives:
            if drive.name == name:
                return drive
        raise ConfigError(
            f"no drive named {name!r}; configured drives: {[d.name for d in self.drives]}"
        )
