"""The YAML configuration of buses and drives, validated into frozen dataclasses.

Every validation error names the file, the key path, the bad value and what is allowed,
and suggests the closest known key for a typo. Nothing in a config is ever evaluated.

What lives where: :mod:`can_config.model` (the dataclasses; each field declares its YAML key,
kind, range, default, unit and description, :mod:`can_config.keys`), :mod:`can_config.fields`
(the checks), this module (parsing a document into the model, loading a file, and back to a
dict, both derived from the declarations).

Owner: none; values only (frozen dataclasses) and pure functions.
"""

from __future__ import annotations

import dataclasses
import difflib
import ipaddress
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from can_config.errors import ConfigError
from can_config.fields import (
    TOP_FIELDS,
    Where,
    check_keys,
    section,
)
from can_config.keys import table, yaml_keys
from can_config.model import (
    DEFAULT_CONFIG,
    DEFAULT_TRAJECTORY_GROUP,
    GEAR_RATIO_MAX,
    GEAR_RATIO_MIN,
    GENERIC_EDS,
    ON_HOST_LOSS,
    BusConfig,
    DriveConfig,
    DriveSystemConfig,
    IdentityConfig,
    RecorderConfig,
    RoverConfig,
    SdoSetting,
    SimModelConfig,
    TrajectoryGroupConfig,
)
from can_config.textfile import load_yaml


def from_yaml(value: float, scale: float) -> float:
    """A YAML number in the key's unit (ms) as the field's (s), at nanosecond resolution: so that a
    config comes back unchanged from :func:`config_to_dict` (``0.1 * 1000 / 1000`` is not always 0.1)."""
    return round(value / scale, 9)


def to_yaml(value: float, scale: float) -> float:
    """A field's value back in its key's unit (the inverse of :func:`from_yaml`)."""
    return round(value * scale, 6)


def build(where: Where, prefix: str, data: Any, cls: type) -> dict[str, Any]:
    """One section of ``cls`` (a dataclass whose fields declare their keys): each key checked and
    converted, nested sections built, times scaled; returns the fields' values by field name."""
    values = section(where, prefix, data, table(cls))
    out: dict[str, Any] = {}
    for yaml_name, (name, spec) in yaml_keys(cls).items():
        value = values[yaml_name]
        if spec.nested is not None and spec.kind == "list":
            value = tuple(spec.nested(**build(where, f"{prefix}{yaml_name}[{k}].", entry, spec.nested))
                          for k, entry in enumerate(value))
        elif spec.nested is not None:
            value = spec.nested(**build(where, f"{prefix}{yaml_name}.", value, spec.nested))
        elif spec.scale != 1.0 and value is not None:
            value = from_yaml(value, spec.scale)
        out[name] = value
    return out


def dump(obj: Any) -> dict[str, Any]:
    """A section back in its YAML shape: every key, in the key's own unit."""
    out: dict[str, Any] = {}
    for yaml_name, (name, spec) in yaml_keys(type(obj)).items():
        value = getattr(obj, name)
        if spec.nested is not None and spec.kind == "list":
            value = [dump(entry) for entry in value]
        elif spec.nested is not None:
            value = dump(value)
        elif isinstance(value, Path):
            value = str(value)
        elif isinstance(value, Mapping):
            value = dict(value)
        elif isinstance(value, tuple):
            value = list(value)
        elif spec.scale != 1.0 and value is not None:
            value = to_yaml(value, spec.scale)
        out[yaml_name] = value
    return out


def parse_config(data: Any, source: Path | str | None = None) -> RoverConfig:
    """Validate an already-parsed YAML document into a :class:`RoverConfig`."""
    where = Where(source)
    base_dir = resolved(Path(source)).parent if source is not None else Path.cwd()
    if not isinstance(data, Mapping):
        raise where.fail("(top level)", f"got {type(data).__name__}; expected a mapping with keys"
                         f" {', '.join(TOP_FIELDS)}.")
    check_keys(where, "", data, TOP_FIELDS)
    buses = _parse_buses(where, data.get("buses"))
    raw_drives = data.get("drives")
    if not isinstance(raw_drives, list) or not raw_drives:
        raise where.fail("drives", "expected a non-empty list of drives.")
    drives = [_parse_drive(where, f"drives[{i}].", raw, buses, base_dir) for i, raw in enumerate(raw_drives)]
    _check_unique(where, drives)
    drive_system = None
    if data.get("drive_system") is not None:
        drive_system = _parse_drive_system(where, data["drive_system"], {d.name for d in drives})
    recorder = build(where, "recorder.", data.get("recorder") or {}, RecorderConfig)
    if recorder["dir"] is not None:
        recorder["dir"] = resolved(base_dir / Path(recorder["dir"]).expanduser())
    groups = _parse_trajectory_groups(where, data.get("trajectory_groups"), drives)
    return RoverConfig(tuple(buses), tuple(drives), drive_system,
                       Path(source) if source is not None else None, RecorderConfig(**recorder), groups)


def _parse_buses(where: Where, raw_buses: Any) -> list[BusConfig]:
    if not isinstance(raw_buses, list) or not raw_buses:
        raise where.fail("buses", "expected a non-empty list of buses.")
    buses = [BusConfig(**build(where, f"buses[{i}].", raw, BusConfig)) for i, raw in enumerate(raw_buses)]
    for i, bus in enumerate(buses):
        # python-can's own arguments from the bus's keys: in kwargs they replaced them unseen (a
        # channel there slipped past every check of the bus's channel)
        shadowed = sorted(set(bus.kwargs) & {"interface", "channel", "bitrate"})
        if shadowed:
            raise where.fail(f"buses[{i}].kwargs", f"sets {', '.join(shadowed)}, which are the bus's own keys; give"
                             f" {' and '.join(shadowed)} as keys of the bus, not in kwargs.")
    names = [b.name for b in buses]
    if len(set(names)) != len(names):
        raise where.fail("buses", f"bus names must be unique; got {names}.")
    return buses


def _parse_drive(where: Where, prefix: str, raw: Any, buses: list[BusConfig], base_dir: Path) -> DriveConfig:
    names = [b.name for b in buses]
    values = build(where, prefix, raw, DriveConfig)
    bus = values["bus"] or buses[0].name
    if bus not in names:
        hint = difflib.get_close_matches(bus, names, n=1)
        raise where.fail(prefix + "bus", f"got {bus!r}; expected one of the configured buses"
                         f" {names}.{' Did you mean ' + repr(hint[0]) + '?' if hint else ''}")
    values["bus"] = bus
    values["eds"] = resolve_eds_path(values["eds"], base_dir)
    bus_cfg = buses[names.index(bus)]
    if values["host_timeout_s"] is None:
        values["host_timeout_s"] = round(3 * bus_cfg.host_heartbeat_s, 9)
    drive = DriveConfig(**values)
    _check_drive(where, prefix, drive)
    if drive.node_id == bus_cfg.host_node_id:
        raise where.fail(prefix + "node_id", f"node id {drive.node_id} is the host's own id on bus {bus!r}"
                         f" (host_node_id, default 127); give the drive another id or set the bus's"
                         " host_node_id to a free one.")
    # judged as the drive holds it (0x1016: whole milliseconds): 50.4 against a 50 ms heartbeat was 50
    timeout_ms = None if drive.host_timeout_s is None else drive.host_timeout_s * 1000
    if timeout_ms is not None and round(timeout_ms) <= bus_cfg.host_heartbeat_s * 1000:
        held = "" if round(timeout_ms) == timeout_ms else f", which the drive holds as {round(timeout_ms)} ms"
        raise where.fail(prefix + "host_timeout_ms", f"got {timeout_ms:g}{held}; it must be"
                         f" longer than the bus's host_heartbeat_ms ({bus_cfg.host_heartbeat_s * 1000:g}),"
                         " typically 3x.")
    return drive


def _parse_drive_system(where: Where, raw: Any, known: set[str]) -> DriveSystemConfig:
    values = build(where, "drive_system.", raw, DriveSystemConfig)
    for side in ("left", "right"):
        for name in values[side]:
            if name not in known:
                raise where.fail(f"drive_system.{side}", f"names drive {name!r}, which is not"
                                 f" configured; configured drives: {sorted(known)}.")
        twice = sorted({name for name in values[side] if list(values[side]).count(name) > 1})
        if twice:  # its speed sent twice a tick, its travel counted twice in the odometry
            raise where.fail(f"drive_system.{side}", f"names {', '.join(map(repr, twice))} more than once; name each"
                             " wheel once.")
    both = sorted(set(values["left"]) & set(values["right"]))
    if both:  # told the left and the right speed each tick (opposite in a spin), counted on both sides
        raise where.fail("drive_system.right", f"names {', '.join(map(repr, both))}, also on the left; a wheel is on"
                         " one side: remove it from the other.")
    return DriveSystemConfig(**values)


def _parse_trajectory_groups(where: Where, raw: Any, drives: list[DriveConfig]) -> tuple[TrajectoryGroupConfig, ...]:
    """The groups given, or (no ``trajectory_groups`` key) one group of every limited joint
    (:data:`DEFAULT_TRAJECTORY_GROUP`) where the config has any; ``[]``: none."""
    if raw is None:
        arm = [d.name for d in drives if d.joint == "limited"]
        raw = [{"name": DEFAULT_TRAJECTORY_GROUP, "joints": arm}] if arm else []
    if not isinstance(raw, list):
        raise where.fail("trajectory_groups", f"got {raw!r}; expected a list of groups ({{name, joints}}).")
    by_name = {d.name: d for d in drives}
    groups: list[TrajectoryGroupConfig] = []
    owner: dict[str, str] = {}
    for i, entry in enumerate(raw):
        prefix = f"trajectory_groups[{i}]."
        group = TrajectoryGroupConfig(**build(where, prefix, entry, TrajectoryGroupConfig))
        if group.name in {g.name for g in groups}:
            raise where.fail(prefix + "name", f"{group.name!r} is used twice; group names must be unique.")
        for name in group.joints:
            drive = by_name.get(name)
            if drive is None:
                raise where.fail(prefix + "joints", f"names drive {name!r}, which is not configured; configured"
                                 f" drives: {sorted(by_name)}.")
            if drive.joint != "limited":
                raise where.fail(prefix + "joints", f"{name!r} is a continuous joint; a trajectory group takes limited"
                                 " joints only (joint: limited, min_deg, max_deg).")
            if name in owner:
                raise where.fail(prefix + "joints", f"{name!r} is in group {owner[name]!r} already; a joint is in one"
                                 " group at most.")
            owner[name] = group.name
        buses = sorted({by_name[n].bus for n in group.joints})
        if len(buses) > 1:
            raise where.fail(prefix + "joints", f"the joints are on buses {buses}; a group follows one bus's SYNC"
                             " clock: put its joints on one bus, or make a group per bus.")
        groups.append(group)
    return tuple(groups)


def _check_drive(where: Where, prefix: str, drive: DriveConfig) -> None:
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


def _check_unique(where: Where, drives: list[DriveConfig]) -> None:
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


#: The environment variable naming the config file that ``load_config()`` reads when given no
#: path (a rover's own file on the Orin; a simulator on another port in tests).
CONFIG_ENV = "ROVERCAN_CONFIG"


def load_config(path: Path | str | None = None) -> RoverConfig:
    """Read and validate a YAML config; ``None`` loads the file named by ``$ROVERCAN_CONFIG``
    when it is set, else the embedded default."""
    if path is None:
        path = os.environ.get(CONFIG_ENV) or None
    source = Path(path) if path is not None else DEFAULT_CONFIG
    data = load_yaml(source, "config file")
    return parse_config(data, source)


def simulated_config(path: Path | str | None, who: str) -> RoverConfig:
    """The config of a run on the simulator (``who``: the demo, a launch's ``sim:=true``): ``path``,
    else the embedded default; never ``$ROVERCAN_CONFIG``, which names the rover's real buses where it
    is deployed (the image sets it). A bus the simulator cannot serve (any interface but socketcand:
    a kernel SocketCAN bus, a real adapter) is refused, nothing opened."""
    config = load_config(path or DEFAULT_CONFIG)
    real = [f"{b.name} ({b.interface} {b.channel}{_remote_host(b)})" for b in config.buses
            if b.interface != "socketcand" or _remote_host(b)]
    if real:
        raise ConfigError(f"{who} runs on the simulator, and {', '.join(real)} would be a real bus: give it a config"
                          " whose buses are socketcand on this host (127.0.0.1: the simulator's), or run the rover"
                          " without the simulator")
    return config


def _remote_host(bus: BusConfig) -> str:
    """`` on HOST`` for a socketcand bus whose server is not on this host (a real socketcand daemon
    beside real drives: the simulator serves loopback only), else ""."""
    host = str(bus.kwargs.get("host", "127.0.0.1"))
    try:
        local = host == "localhost" or ipaddress.ip_address(host).is_loopback
    except ValueError:  # a name: not the simulator's
        local = False
    return "" if local else f" on {host}"


def config_to_dict(config: RoverConfig) -> dict[str, Any]:
    """Back to the YAML shape (used to hand a config to a subprocess or a ROS parameter):
    ``parse_config(config_to_dict(c)) == c``."""
    out: dict[str, Any] = {"buses": [dump(b) for b in config.buses], "drives": [dump(d) for d in config.drives],
                           "recorder": dump(config.recorder)}
    if config.drive_system is not None:
        out["drive_system"] = dump(config.drive_system)
    out["trajectory_groups"] = [dump(g) for g in config.trajectory_groups]
    return out


def with_bus_overrides(config: RoverConfig, **kwargs: Any) -> RoverConfig:
    """A copy whose buses all get ``kwargs`` merged into their python-can arguments
    (e.g. ``port=`` of a simulator started on a free port)."""
    buses = tuple(dataclasses.replace(b, kwargs={**b.kwargs, **kwargs}) for b in config.buses)
    return dataclasses.replace(config, buses=buses)


# the names callers imported from here before the split (can_config.config stays their door)
__all__ = ["CONFIG_ENV", "DEFAULT_CONFIG", "GEAR_RATIO_MAX", "GEAR_RATIO_MIN", "GENERIC_EDS", "ON_HOST_LOSS", "BusConfig", "DriveConfig",
           "DriveSystemConfig", "IdentityConfig", "RecorderConfig", "RoverConfig", "SdoSetting", "SimModelConfig",
           "TrajectoryGroupConfig", "config_to_dict", "load_config", "parse_config", "resolve_eds_path", "resolved", "with_bus_overrides"]
