"""The YAML configuration of buses and drives, validated into frozen dataclasses.

Every validation error names the file, the key path, the bad value and what is allowed,
and suggests the closest known key for a typo. Nothing in a config is ever evaluated.
"""

from __future__ import annotations

import dataclasses
import difflib
import math
import os
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from can_config.errors import ConfigError
from can_config.textfile import load_yaml

DATA_DIR = Path(__file__).resolve().parent / "data"
GENERIC_EDS = DATA_DIR / "generic_cia402.eds"
DEFAULT_CONFIG = DATA_DIR / "default.yaml"

#: ``on_host_loss`` -> the CiA 402 abort connection option code (0x6007) written at boot.
ON_HOST_LOSS = {"quick_stop": 3, "disable": 2, "fault": 1}

_NAME_RE = re.compile(r"^[A-Za-z][A-Za-z0-9_]*$")
_REQUIRED: Any = object()


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


# --------------------------------------------------------------------------- validation


@dataclass(frozen=True)
class _Field:
    kind: str  # "int", "float", "bool", "str", "name", "namespace", "path", "map", "list", "list_names",
    #            "opt_float", "opt_int" (a byte size), "number" (int or float)
    default: Any = _REQUIRED
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] | None = None
    low_open: bool = False


_BUS_FIELDS: dict[str, _Field] = {
    "name": _Field("name"),
    "interface": _Field("str"),
    "channel": _Field("str"),
    "bitrate": _Field("int", 1_000_000, 10_000, 8_000_000),
    "kwargs": _Field("map", {}),
    "sync_period_ms": _Field("float", 10.0, 1.0, 1000.0),
    "host_node_id": _Field("int", 127, 1, 127),
    "host_heartbeat_ms": _Field("float", 50.0, 10.0, 1000.0),
    "connect_timeout_ms": _Field("float", 10_000.0, 0.0, 600_000.0),
    "sync_timer": _Field("str", "auto", choices=("auto", "thread")),
}

_IDENTITY_FIELDS: dict[str, _Field] = {
    "vendor_id": _Field("int", None, 0, 0xFFFF_FFFF),
    "product_code": _Field("int", None, 0, 0xFFFF_FFFF),
    "revision": _Field("int", None, 0, 0xFFFF_FFFF),
}

_DRIVE_FIELDS: dict[str, _Field] = {
    "name": _Field("name"),
    "namespace": _Field("namespace", ""),
    "node_id": _Field("int", _REQUIRED, 1, 127),
    "bus": _Field("str", None),
    "eds": _Field("path", "generic"),
    "counts_per_rev": _Field("int", None, 1, 2**31 - 1),
    "gear_ratio": _Field("float", 1.0, GEAR_RATIO_MIN, GEAR_RATIO_MAX),
    "rated_torque_nm": _Field("float", 1.0, 0.0, 1e5, low_open=True),
    "max_torque_nm": _Field("opt_float", None, 0.0, 1e6, low_open=True),
    "joint": _Field("str", "continuous", choices=("continuous", "limited")),
    "min_deg": _Field("opt_float", None, -1e7, 1e7),
    "max_deg": _Field("opt_float", None, -1e7, 1e7),
    "max_velocity_deg_s": _Field("float", 360.0, 0.0, 1e6, low_open=True),
    "profile_velocity_deg_s": _Field("float", 90.0, 0.0, 1e6, low_open=True),
    "profile_acceleration_deg_s2": _Field("float", 360.0, 0.0, 1e7, low_open=True),
    "heartbeat_period_ms": _Field("float", 100.0, 10.0, 10_000.0),
    "heartbeat_timeout_ms": _Field("float", 350.0, 20.0, 60_000.0),
    "watchdog_ms": _Field("float", 500.0, 10.0, 60_000.0),
    "arm_on_start": _Field("bool", False),
    "restore_enable_after_reboot": _Field("bool", False),
    "homing_method": _Field("int", 35, -128, 127),
    "homing_speed_deg_s": _Field("float", 30.0, 0.0, 1e6, low_open=True),
    "homing_timeout_s": _Field("float", 10.0, 0.1, 600.0),
    "identity": _Field("map", {}),
    "invert": _Field("bool", False),
    "offset_deg": _Field("float", 0.0, -1e6, 1e6),
    "quick_stop_deceleration_deg_s2": _Field("opt_float", None, 0.0, 1e7, low_open=True),
    "host_timeout_ms": _Field("opt_float", None, 20.0, 65_535.0),
    "on_host_loss": _Field("str", "quick_stop", choices=tuple(ON_HOST_LOSS)),
    "allow_no_host_watch": _Field("bool", False),
    "host_watch": _Field("str", "auto", choices=("auto", "heartbeat", "guarding")),
    "stale_after_syncs": _Field("int", 5, 2, 1000),
    "sdo_timeout_ms": _Field("float", 500.0, 10.0, 10_000.0),
    "boot_timeout_ms": _Field("float", 2000.0, 100.0, 60_000.0),
    "sdo": _Field("list", []),
    "velocity_mode": _Field("str", "profile", choices=("profile", "cyclic")),
    "torque_mode": _Field("str", "profile", choices=("profile", "cyclic")),
    "sim": _Field("map", {}),
}

_SIM_FIELDS: dict[str, _Field] = {
    "inertia_kg_m2": _Field("float", 1e-4, 0.0, 100.0, low_open=True),
    "viscous_nm_s_rad": _Field("float", 2e-5, 0.0, 100.0),
    "coulomb_nm": _Field("float", 0.03, 0.0, 1e4),
    "load_nm": _Field("float", 0.0, -1e4, 1e4),
    "torque_lag_ms": _Field("float", 1.0, 0.0, 100.0),
    "bandwidth_hz": _Field("float", 50.0, 0.0, 1000.0, low_open=True),
    "position_kp": _Field("opt_float", None, 0.0, 1e4),
    "velocity_kp": _Field("opt_float", None, 0.0, 1e4),
    "velocity_ki": _Field("opt_float", None, 0.0, 1e6),
    "velocity_ff": _Field("float", 1.0, 0.0, 2.0),
}

_SDO_FIELDS: dict[str, _Field] = {
    "index": _Field("int", _REQUIRED, 0x1000, 0xFFFF),
    "sub": _Field("int", 0, 0, 255),
    "value": _Field("number", _REQUIRED),
    "check": _Field("bool", True),
    "size": _Field("opt_int", None, 1, 8),
}

_DRIVE_SYSTEM_FIELDS: dict[str, _Field] = {
    "left": _Field("list_names"),
    "right": _Field("list_names"),
    "track_width_m": _Field("float", 0.6, 0.0, 100.0, low_open=True),
    "wheel_radius_m": _Field("float", 0.1, 0.0, 10.0, low_open=True),
    "cmd_timeout_ms": _Field("float", 500.0, 10.0, 60_000.0),
    "max_accel_m_s2": _Field("float", 1.0, 0.0, 100.0, low_open=True),
    "max_speed_m_s": _Field("float", 1.0, 0.0, 100.0, low_open=True),
    "max_angular_rad_s": _Field("float", 2.0, 0.0, 100.0, low_open=True),
}

_RECORDER_FIELDS: dict[str, _Field] = {
    "enabled": _Field("bool", True),
    "dir": _Field("str", None),
    "seconds": _Field("float", 10.0, 1.0, 600.0),
    "after_s": _Field("float", 1.0, 0.0, 60.0),
    "max_mb": _Field("float", 200.0, 1.0, 1e6),
    "plot": _Field("bool", True),
}

_TOP_FIELDS = ("buses", "drives", "drive_system", "recorder")


class _Where:
    """Formats error locations: ``file: drives[0].gear_ratio``."""

    def __init__(self, source: Path | str | None) -> None:
        self.source = str(source) if source is not None else "<config>"

    def fail(self, key: str, message: str) -> ConfigError:
        return ConfigError(f"{self.source}: {key}: {message}")


def _check_keys(where: _Where, prefix: str, data: Mapping[str, Any], known: tuple[str, ...]) -> None:
    for key in data:
        if key not in known:
            hint = difflib.get_close_matches(str(key), known, n=1)
            suggestion = f" Did you mean {hint[0]!r}?" if hint else ""
            raise where.fail(
                f"{prefix}{key}",
                f"unknown key.{suggestion} Allowed keys: {', '.join(known)}.",
            )


def _convert(where: _Where, key: str, value: Any, spec: _Field) -> Any:
    if value is None and spec.default is None:
        return None
    kind = spec.kind
    if kind == "bool":
        if not isinstance(value, bool):
            raise where.fail(key, f"got {value!r} ({type(value).__name__}); expected true or false.")
        return value
    if kind == "int":
        if isinstance(value, bool) or not isinstance(value, int):
            raise where.fail(key, f"got {value!r} ({type(value).__name__}); expected a whole number"
                             f" from {spec.low:g} to {spec.high:g}.")
        _check_range(where, key, value, spec)
        return value
    if kind in ("float", "opt_float"):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise where.fail(key, f"got {value!r} ({type(value).__name__}); expected a number"
                             f"{_range_text(spec)}.")
        number = float(value)
        if not math.isfinite(number):
            raise where.fail(key, f"got {value!r}; expected a finite number{_range_text(spec)}.")
        _check_range(where, key, number, spec)
        return number
    if kind in ("str", "name", "path"):
        if not isinstance(value, str) or not value:
            raise where.fail(key, f"got {value!r} ({type(value).__name__}); expected a non-empty text.")
        if kind == "name" and not _NAME_RE.match(value):
            raise where.fail(key, f"got {value!r}; expected a name of letters, digits and '_' that"
                             " starts with a letter (it becomes part of ROS topic names).")
        if spec.choices is not None and value not in spec.choices:
            raise where.fail(key, f"got {value!r}; expected one of {', '.join(spec.choices)}.")
        return value
    if kind == "namespace":
        tokens = value.strip("/").split("/") if isinstance(value, str) else None
        if tokens is None or (value and not all(_NAME_RE.match(t) for t in tokens)):
            raise where.fail(key, f"got {value!r}; expected a ROS namespace: names of letters, digits and"
                             " '_' that start with a letter, separated by '/' (e.g. wheels/left), or ''.")
        return value
    if kind == "map":
        if not isinstance(value, Mapping):
            raise where.fail(key, f"got {value!r} ({type(value).__name__}); expected a mapping (key: value).")
        return dict(value)
    if kind == "list":
        if not isinstance(value, list):
            raise where.fail(key, f"got {value!r} ({type(value).__name__}); expected a list.")
        return list(value)
    if kind == "number":
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            raise where.fail(key, f"got {value!r}; expected a finite number (decimal, 0x hex or a real).")
        return value
    if kind == "opt_int":
        if isinstance(value, bool) or not isinstance(value, int) or value not in (1, 2, 4, 8):
            raise where.fail(key, f"got {value!r}; expected 1, 2, 4 or 8 (bytes).")
        return value
    if kind == "list_names":
        if not isinstance(value, list) or not value or not all(isinstance(v, str) for v in value):
            raise where.fail(key, f"got {value!r}; expected a non-empty list of drive names.")
        return tuple(value)
    raise AssertionError(f"unknown field kind {kind}")  # pragma: no cover - programming error


def _range_text(spec: _Field) -> str:
    if spec.low is None or spec.high is None:
        return ""
    low_op = ">" if spec.low_open else ">="
    return f" {low_op} {spec.low:g} and <= {spec.high:g}"


def _check_range(where: _Where, key: str, value: float, spec: _Field) -> None:
    if spec.low is None or spec.high is None:
        return
    too_low = value <= spec.low if spec.low_open else value < spec.low
    if too_low or value > spec.high:
        raise where.fail(key, f"got {value!r}; expected a value{_range_text(spec)}.")


def _section(where: _Where, prefix: str, data: Any, fields: dict[str, _Field]) -> dict[str, Any]:
    if not isinstance(data, Mapping):
        raise where.fail(prefix.rstrip("."), f"got {data!r}; expected a mapping of keys.")
    _check_keys(where, prefix, data, tuple(fields))
    out: dict[str, Any] = {}
    for key, spec in fields.items():
        if key in data:
            out[key] = _convert(where, prefix + key, data[key], spec)
        elif spec.default is _REQUIRED:
            raise where.fail(prefix + key, "missing; this key is required.")
        else:
            out[key] = spec.default
    return out


def parse_config(data: Any, source: Path | str | None = None) -> RoverConfig:
    """Validate an already-parsed YAML document into a :class:`RoverConfig`."""
    where = _Where(source)
    base_dir = resolved(Path(source)).parent if source is not None else Path.cwd()
    if not isinstance(data, Mapping):
        raise where.fail("(top level)", f"got {type(data).__name__}; expected a mapping with keys"
                         f" {', '.join(_TOP_FIELDS)}.")
    _check_keys(where, "", data, _TOP_FIELDS)
    raw_buses = data.get("buses")
    if not isinstance(raw_buses, list) or not raw_buses:
        raise where.fail("buses", "expected a non-empty list of buses.")
    buses: list[BusConfig] = []
    for i, raw in enumerate(raw_buses):
        values = _section(where, f"buses[{i}].", raw, _BUS_FIELDS)
        period_ms = values.pop("sync_period_ms")
        host_ms = values.pop("host_heartbeat_ms")
        connect_ms = values.pop("connect_timeout_ms")
        buses.append(BusConfig(sync_period_s=period_ms / 1000.0, host_heartbeat_s=host_ms / 1000.0,
                               connect_timeout_s=connect_ms / 1000.0, **values))
    names = [b.name for b in buses]
    if len(set(names)) != len(names):
        raise where.fail("buses", f"bus names must be unique; got {names}.")

    raw_drives = data.get("drives")
    if not isinstance(raw_drives, list) or not raw_drives:
        raise where.fail("drives", "expected a non-empty list of drives.")
    drives: list[DriveConfig] = []
    for i, raw in enumerate(raw_drives):
        prefix = f"drives[{i}]."
        values = _section(where, prefix, raw, _DRIVE_FIELDS)
        bus = values["bus"] or buses[0].name
        if bus not in names:
            hint = difflib.get_close_matches(bus, names, n=1)
            raise where.fail(prefix + "bus", f"got {bus!r}; expected one of the configured buses"
                             f" {names}.{' Did you mean ' + repr(hint[0]) + '?' if hint else ''}")
        values["bus"] = bus
        values["eds"] = resolve_eds_path(values["eds"], base_dir)
        identity = _section(where, prefix + "identity.", values["identity"], _IDENTITY_FIELDS)
        values["identity"] = IdentityConfig(**identity)
        values["sdo"] = tuple(SdoSetting(**_section(where, f"{prefix}sdo[{k}].", entry, _SDO_FIELDS))
                              for k, entry in enumerate(values["sdo"]))
        sim = _section(where, prefix + "sim.", values["sim"], _SIM_FIELDS)
        sim["torque_lag_s"] = sim.pop("torque_lag_ms") / 1000.0
        values["sim"] = SimModelConfig(**sim)
        for ms_key, s_key in (("heartbeat_period_ms", "heartbeat_period_s"),
                              ("heartbeat_timeout_ms", "heartbeat_timeout_s"),
                              ("watchdog_ms", "watchdog_s"), ("sdo_timeout_ms", "sdo_timeout_s"),
                              ("boot_timeout_ms", "boot_timeout_s")):
            values[s_key] = values.pop(ms_key) / 1000.0
        host_ms = values.pop("host_timeout_ms")
        bus_cfg = buses[names.index(bus)]
        values["host_timeout_s"] = host_ms / 1000.0 if host_ms is not None else 3 * bus_cfg.host_heartbeat_s
        drive = DriveConfig(**values)
        _check_drive(where, prefix, drive)
        if drive.node_id == bus_cfg.host_node_id:
            raise where.fail(prefix + "node_id", f"node id {drive.node_id} is the host's own id on bus {bus!r}"
                             f" (host_node_id, default 127); give the drive another id or set the bus's"
                             " host_node_id to a free one.")
        if drive.host_timeout_s is not None and drive.host_timeout_s <= bus_cfg.host_heartbeat_s:
            raise where.fail(prefix + "host_timeout_ms", f"got {drive.host_timeout_s * 1000:g}; it must be"
                             f" longer than the bus's host_heartbeat_ms ({bus_cfg.host_heartbeat_s * 1000:g}),"
                             " typically 3x.")
        drives.append(drive)
    _check_unique(where, drives)

    drive_system = None
    if data.get("drive_system") is not None:
        values = _section(where, "drive_system.", data["drive_system"], _DRIVE_SYSTEM_FIELDS)
        known = {d.name for d in drives}
        for side in ("left", "right"):
            for name in values[side]:
                if name not in known:
                    raise where.fail(f"drive_system.{side}", f"names drive {name!r}, which is not"
                                     f" configured; configured drives: {sorted(known)}.")
        values["cmd_timeout_s"] = values.pop("cmd_timeout_ms") / 1000.0
        drive_system = DriveSystemConfig(**values)
    recorder = _section(where, "recorder.", data.get("recorder") or {}, _RECORDER_FIELDS)
    if recorder["dir"] is not None:
        recorder["dir"] = resolved(base_dir / Path(recorder["dir"]).expanduser())
    return RoverConfig(tuple(buses), tuple(drives), drive_system,
                       Path(source) if source is not None else None, RecorderConfig(**recorder))


def _check_drive(where: _Where, prefix: str, drive: DriveConfig) -> None:
    if drive.joint == "limited":
        if drive.min_deg is None or drive.max_deg is None:
            raise where.fail(prefix + "joint", "a limited joint needs min_deg and max_deg.")
        if drive.min_deg >= drive.max_deg:
            raise where.fail(prefix + "min_deg", f"got min_deg={drive.min_deg:g} >= max_deg="
                             f"{drive.max_deg:g}; min_deg must be below max_deg.")
    elif drive.min_deg is not None or drive.max_deg is not None:
        raise where.fail(prefix + "joint", "min_deg/max_deg are only allowed with joint: limited.")
    if drive.heartbeat_timeout_s <= drive.heartbeat_period_s:
        raise where.fail(prefix + "heartbeat_timeout_ms", f"got {drive.heartbeat_timeout_s * 1000:g};"
                         f" it must be longer than heartbeat_period_ms"
                         f" ({drive.heartbeat_period_s * 1000:g}), typically 1.5x to 3x.")
    if drive.profile_velocity_deg_s > drive.max_velocity_deg_s:
        raise where.fail(prefix + "profile_velocity_deg_s", f"got {drive.profile_velocity_deg_s:g};"
                         f" it must not exceed max_velocity_deg_s ({drive.max_velocity_deg_s:g}).")


def _check_unique(where: _Where, drives: list[DriveConfig]) -> None:
    seen_names: set[str] = set()
    seen_ids: set[tuple[str, int]] = set()
    for i, drive in enumerate(drives):
        if drive.name in seen_names:
            raise where.fail(f"drives[{i}].name", f"{drive.name!r} is used twice; names must be unique.")
        if (drive.bus, drive.node_id) in seen_ids:
            raise where.fail(f"drives[{i}].node_id", f"node id {drive.node_id} is used twice on bus"
                             f" {drive.bus!r}; each drive on a bus needs its own id (1..127).")
        seen_names.add(drive.name)
        seen_ids.add((drive.bus, drive.node_id))


def resolve_eds_path(value: str, base_dir: Path) -> Path:
    """``generic`` is the project's own CiA 402 EDS; other paths are relative to the config."""
    if value == "generic":
        return GENERIC_EDS
    path = Path(value).expanduser()
    return path if path.is_absolute() else resolved(base_dir / path)


def resolved(path: Path) -> Path:
    """``path.resolve()``, or :class:`ConfigError` naming a symlink loop."""
    try:
        return path.resolve()
    except (OSError, RuntimeError) as err:  # a symlink loop: RuntimeError before Python 3.13
        raise ConfigError(f"{path}: cannot resolve the path ({err}); check its symlinks.") from err


def load_config(path: Path | str | None = None) -> RoverConfig:
    """Read and validate a YAML config; ``None`` loads the embedded default."""
    source = Path(path) if path is not None else DEFAULT_CONFIG
    data = load_yaml(source, "config file")
    return parse_config(data, source)


def config_to_dict(config: RoverConfig) -> dict[str, Any]:
    """Back to the YAML shape (used to hand a config to a subprocess or a ROS parameter)."""
    buses = [{"name": b.name, "interface": b.interface, "channel": b.channel, "bitrate": b.bitrate,
              "kwargs": dict(b.kwargs), "sync_period_ms": b.sync_period_s * 1000.0,
              "host_node_id": b.host_node_id, "host_heartbeat_ms": b.host_heartbeat_s * 1000.0,
              "connect_timeout_ms": b.connect_timeout_s * 1000.0, "sync_timer": b.sync_timer}
             for b in config.buses]
    drives = []
    for d in config.drives:
        entry: dict[str, Any] = {
            "name": d.name, "namespace": d.namespace, "node_id": d.node_id, "bus": d.bus, "eds": str(d.eds),
            "counts_per_rev": d.counts_per_rev, "gear_ratio": d.gear_ratio,
            "rated_torque_nm": d.rated_torque_nm, "max_torque_nm": d.max_torque_nm, "joint": d.joint,
            "max_velocity_deg_s": d.max_velocity_deg_s,
            "profile_velocity_deg_s": d.profile_velocity_deg_s,
            "profile_acceleration_deg_s2": d.profile_acceleration_deg_s2,
            "heartbeat_period_ms": d.heartbeat_period_s * 1000.0,
            "heartbeat_timeout_ms": d.heartbeat_timeout_s * 1000.0,
            "watchdog_ms": d.watchdog_s * 1000.0, "arm_on_start": d.arm_on_start,
            "restore_enable_after_reboot": d.restore_enable_after_reboot,
            "homing_method": d.homing_method, "homing_speed_deg_s": d.homing_speed_deg_s,
            "homing_timeout_s": d.homing_timeout_s,
            "identity": {k: v for k, v in vars(d.identity).items() if v is not None},
            "invert": d.invert, "offset_deg": d.offset_deg,
            "quick_stop_deceleration_deg_s2": d.quick_stop_deceleration_deg_s2,
            "host_timeout_ms": d.host_timeout_s * 1000.0 if d.host_timeout_s is not None else None,
            "on_host_loss": d.on_host_loss, "allow_no_host_watch": d.allow_no_host_watch, "host_watch": d.host_watch,
            "stale_after_syncs": d.stale_after_syncs,
            "sdo_timeout_ms": d.sdo_timeout_s * 1000.0, "boot_timeout_ms": d.boot_timeout_s * 1000.0,
            "sdo": [{k: v for k, v in vars(x).items() if v is not None} for x in d.sdo],
            "velocity_mode": d.velocity_mode, "torque_mode": d.torque_mode,
            "sim": _sim_to_dict(d.sim),
        }
        if d.joint == "limited":
            entry["min_deg"] = d.min_deg
            entry["max_deg"] = d.max_deg
        drives.append(entry)
    rec = config.recorder
    out: dict[str, Any] = {"buses": buses, "drives": drives,
                           "recorder": {"enabled": rec.enabled, "seconds": rec.seconds, "after_s": rec.after_s,
                                        "max_mb": rec.max_mb, "plot": rec.plot,
                                        **({"dir": str(rec.dir)} if rec.dir is not None else {})}}
    if config.drive_system is not None:
        ds = config.drive_system
        out["drive_system"] = {"left": list(ds.left), "right": list(ds.right),
                               "track_width_m": ds.track_width_m, "wheel_radius_m": ds.wheel_radius_m,
                               "cmd_timeout_ms": ds.cmd_timeout_s * 1000.0,
                               "max_accel_m_s2": ds.max_accel_m_s2, "max_speed_m_s": ds.max_speed_m_s,
                               "max_angular_rad_s": ds.max_angular_rad_s}
    return out


def _sim_to_dict(sim: SimModelConfig) -> dict[str, Any]:
    out = {k: v for k, v in vars(sim).items() if v is not None}
    out["torque_lag_ms"] = out.pop("torque_lag_s") * 1000.0
    return out


def with_bus_overrides(config: RoverConfig, **kwargs: Any) -> RoverConfig:
    """A copy whose buses all get ``kwargs`` merged into their python-can arguments
    (e.g. ``port=`` of a simulator started on a free port)."""
    buses = tuple(dataclasses.replace(b, kwargs={**b.kwargs, **kwargs}) for b in config.buses)
    return dataclasses.replace(config, buses=buses)
