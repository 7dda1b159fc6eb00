"""The configuration's frozen dataclasses (buses, drives, drive system, recorder) and their
fixed values; what the rest of the stack reads. No parsing here (:mod:`can_config.config`).
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from can_config.errors import ConfigError

DATA_DIR = Path(__file__).resolve().parent / "data"
GENERIC_EDS = DATA_DIR / "generic_cia402.eds"
DEFAULT_CONFIG = DATA_DIR / "default.yaml"
#: The socketcand protocol's usual TCP port: the simulator's default and the driver's when a
#: config's socketcand bus names no port (the driver and the simulator meet only on the bus).
SOCKETCAND_PORT = 29536
#: ``on_host_loss`` -> the CiA 402 abort connection option code (0x6007) written at boot.
ON_HOST_LOSS = {"quick_stop": 3, "disable": 2, "fault": 1}


@dataclass(frozen=True)
class BusConfig:
    """One CAN bus, opened as ``can.Bus(interface=..., channel=..., bitrate=..., **kwargs)``."""

    name: str
    interface: str
    channel: str
    bitrate: int = 1_000_000
    kwargs: Mapping[str, Any] = field(default_factory=dict)
    sync_period_s: float = 0.01
    host_node_id: int = 127  # the driver's own NMT node id: its heartbeat is what the drives watch
    host_heartbeat_s: float = 0.05
    connect_timeout_s: float = 10.0  # how long the driver waits for a socketcand server at start
    #: auto: the bus's own timer sends the SYNC (the kernel's on SocketCAN, the daemon's on
    #: socketcand); thread: a thread of the driver process does
    sync_timer: str = "auto"

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

    vendor_id: int | None = None
    product_code: int | None = None
    revision: int | None = None


@dataclass(frozen=True)
class SdoSetting:
    """One vendor parameter written at boot (``sdo:`` list of a drive), in the list's order."""

    index: int
    sub: int = 0
    value: int | float = 0
    check: bool = True  # read back after the write and compare
    size: int | None = None  # bytes, for an object the EDS does not list (1, 2, 4 or 8)


@dataclass(frozen=True)
class SimModelConfig:
    """The simulator's motor and load model of one drive (``sim:`` of a drive; the driver
    ignores it). Motor side of the gear; the defaults look like one wheel of a ~60 kg
    six-wheeled rover behind a 50:1 gear. Gains left out follow from the inertia and the
    velocity loop's bandwidth."""

    inertia_kg_m2: float = 1e-4
    viscous_nm_s_rad: float = 2e-5
    coulomb_nm: float = 0.03
    load_nm: float = 0.0
    torque_lag_s: float = 0.001
    bandwidth_hz: float = 50.0
    position_kp: float | None = None
    velocity_kp: float | None = None
    velocity_ki: float | None = None
    velocity_ff: float = 1.0


@dataclass(frozen=True)
class DriveConfig:
    """One CiA 402 drive and the joint it moves."""

    name: str
    node_id: int
    bus: str
    eds: Path
    namespace: str = ""  # ROS namespace of the joint's topics and services ("" = the node's)
    counts_per_rev: int | None = None  # None: from the drive (0x608F), else 4096
    gear_ratio: float = 1.0
    rated_torque_nm: float = 1.0
    max_torque_nm: float | None = None  # None: the rated torque at the joint (rated x gear)
    joint: str = "continuous"
    min_deg: float | None = None
    max_deg: float | None = None
    max_velocity_deg_s: float = 360.0
    profile_velocity_deg_s: float = 90.0
    profile_acceleration_deg_s2: float = 360.0
    heartbeat_period_s: float = 0.1
    heartbeat_timeout_s: float = 0.35
    watchdog_s: float = 0.5
    arm_on_start: bool = False
    restore_enable_after_reboot: bool = False
    homing_method: int = 35
    homing_speed_deg_s: float = 30.0
    homing_timeout_s: float = 10.0
    identity: IdentityConfig = field(default_factory=IdentityConfig)
    invert: bool = False  # the joint turns the other way than the motor (a mirrored wheel)
    offset_deg: float = 0.0  # the joint angle at drive position 0
    quick_stop_deceleration_deg_s2: float | None = None  # None: 4x profile_acceleration_deg_s2
    host_timeout_s: float | None = None  # consumer time of the host heartbeat; None: 3x its period
    on_host_loss: str = "quick_stop"  # 0x6007: what the drive does when the host falls silent
    allow_no_host_watch: bool = False  # arm a drive that cannot watch the host (loud warning)
    #: how the drive watches the host: heartbeat consumer (0x1016), node guarding (0x100C/0x100D,
    #: remote frames: kernel buses only), or auto (0x1016 where the drive has it, else guarding)
    host_watch: str = "auto"
    stale_after_syncs: int = 5  # no TPDO for this many SYNC periods: its state is reported stale
    sdo_timeout_s: float = 0.5  # one SDO answer (a parameter save can keep a drive silent ~400 ms)
    boot_timeout_s: float = 2.0  # from NMT reset to the boot-up message
    sdo: tuple[SdoSetting, ...] = ()  # vendor parameters written at boot, in order
    velocity_mode: str = "profile"  # /joint_commands velocity: profile velocity, or cyclic (CSV)
    torque_mode: str = "profile"  # /joint_commands effort: profile torque, or cyclic (CST)
    sim: SimModelConfig = field(default_factory=SimModelConfig)  # the simulator's model of it

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

    left: tuple[str, ...]
    right: tuple[str, ...]
    track_width_m: float = 0.6
    wheel_radius_m: float = 0.1
    cmd_timeout_s: float = 0.5
    max_accel_m_s2: float = 1.0
    max_speed_m_s: float = 1.0  # body speed, and every wheel's rim speed
    max_angular_rad_s: float = 2.0


#: Motor revolutions per joint revolution: below 0.001 a 4096-count encoder gives under 5
#: counts per joint revolution, and a move rounds to no motion at all.
GEAR_RATIO_MIN = 0.001
GEAR_RATIO_MAX = 1e6


@dataclass(frozen=True)
class RecorderConfig:
    """The driver's flight recorder (``recorder:``): the last ``seconds`` of frames and drive
    states, written on each incident with what follows it for ``after_s``."""

    enabled: bool = True
    dir: Path | None = None  # None: $ROVERCAN_INCIDENT_DIR, else ~/.local/state/rovercan/incidents
    seconds: float = 10.0
    after_s: float = 1.0
    max_mb: float = 200.0  # the directory's cap: the oldest incidents go first
    plot: bool = True  # a PNG of angle, velocity, torque and state (needs matplotlib)

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
