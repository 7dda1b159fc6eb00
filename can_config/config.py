"""The YAML configuration of buses and drives, validated into frozen dataclasses.

Every validation error names the file, the key path, the bad value and what is allowed,
and suggests the closest known key for a typo. Nothing in a config is ever evaluated.

What lives where: :mod:`can_config.model` (the dataclasses), :mod:`can_config.fields` (each key's
kind, range and default, and the checks), this module (parsing a document into the model,
loading a file, and back to a dict).
"""

from __future__ import annotations

import dataclasses
import difflib
from collections.abc import Mapping
from pathlib import Path
from typing import Any

from can_config.errors import ConfigError
from can_config.fields import (
    BUS_FIELDS,
    DRIVE_FIELDS,
    DRIVE_SYSTEM_FIELDS,
    IDENTITY_FIELDS,
    RECORDER_FIELDS,
    SDO_FIELDS,
    SIM_FIELDS,
    TOP_FIELDS,
    Where,
    check_keys,
    section,
)
from can_config.model import (
    DEFAULT_CONFIG,
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
)
from can_config.textfile import load_yaml


def ms_to_s(ms: float) -> float:
    """A YAML time in ms as the config's seconds, at nanosecond resolution: so that a config
    comes back unchanged from :func:`config_to_dict` (``0.1 * 1000 / 1000`` is not always 0.1)."""
    return round(ms / 1000.0, 9)


def s_to_ms(seconds: float) -> float:
    """The config's seconds back to ms for YAML (the inverse of :func:`ms_to_s`)."""
    return round(seconds * 1000.0, 6)


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
    recorder = section(where, "recorder.", data.get("recorder") or {}, RECORDER_FIELDS)
    if recorder["dir"] is not None:
        recorder["dir"] = resolved(base_dir / Path(recorder["dir"]).expanduser())
    return RoverConfig(tuple(buses), tuple(drives), drive_system,
                       Path(source) if source is not None else None, RecorderConfig(**recorder))


def _parse_buses(where: Where, raw_buses: Any) -> list[BusConfig]:
    if not isinstance(raw_buses, list) or not raw_buses:
        raise where.fail("buses", "expected a non-empty list of buses.")
    buses: list[BusConfig] = []
    for i, raw in enumerate(raw_buses):
        values = section(where, f"buses[{i}].", raw, BUS_FIELDS)
        period_ms = values.pop("sync_period_ms")
        host_ms = values.pop("host_heartbeat_ms")
        connect_ms = values.pop("connect_timeout_ms")
        buses.append(BusConfig(sync_period_s=ms_to_s(period_ms), host_heartbeat_s=ms_to_s(host_ms),
                               connect_timeout_s=ms_to_s(connect_ms), **values))
    names = [b.name for b in buses]
    if len(set(names)) != len(names):
        raise where.fail("buses", f"bus names must be unique; got {names}.")
    return buses


def _parse_drive(where: Where, prefix: str, raw: Any, buses: list[BusConfig], base_dir: Path) -> DriveConfig:
    names = [b.name for b in buses]
    values = section(where, prefix, raw, DRIVE_FIELDS)
    bus = values["bus"] or buses[0].name
    if bus not in names:
        hint = difflib.get_close_matches(bus, names, n=1)
        raise where.fail(prefix + "bus", f"got {bus!r}; expected one of the configured buses"
                         f" {names}.{' Did you mean ' + repr(hint[0]) + '?' if hint else ''}")
    values["bus"] = bus
    values["eds"] = resolve_eds_path(values["eds"], base_dir)
    identity = section(where, prefix + "identity.", values["identity"], IDENTITY_FIELDS)
    values["identity"] = IdentityConfig(**identity)
    values["sdo"] = tuple(SdoSetting(**section(where, f"{prefix}sdo[{k}].", entry, SDO_FIELDS))
                          for k, entry in enumerate(values["sdo"]))
    sim = section(where, prefix + "sim.", values["sim"], SIM_FIELDS)
    sim["torque_lag_s"] = ms_to_s(sim.pop("torque_lag_ms"))
    values["sim"] = SimModelConfig(**sim)
    for ms_key, s_key in (("heartbeat_period_ms", "heartbeat_period_s"),
                          ("heartbeat_timeout_ms", "heartbeat_timeout_s"),
                          ("watchdog_ms", "watchdog_s"), ("sdo_timeout_ms", "sdo_timeout_s"),
                          ("boot_timeout_ms", "boot_timeout_s")):
        values[s_key] = ms_to_s(values.pop(ms_key))
    host_ms = values.pop("host_timeout_ms")
    bus_cfg = buses[names.index(bus)]
    values["host_timeout_s"] = ms_to_s(host_ms) if host_ms is not None else round(3 * bus_cfg.host_heartbeat_s, 9)
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
    return drive


def _parse_drive_system(where: Where, raw: Any, known: set[str]) -> DriveSystemConfig:
    values = section(where, "drive_system.", raw, DRIVE_SYSTEM_FIELDS)
    for side in ("left", "right"):
        for name in values[side]:
            if name not in known:
                raise where.fail(f"drive_system.{side}", f"names drive {name!r}, which is not"
                                 f" configured; configured drives: {sorted(known)}.")
    values["cmd_timeout_s"] = ms_to_s(values.pop("cmd_timeout_ms"))
    return DriveSystemConfig(**values)


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


def load_config(path: Path | str | None = None) -> RoverConfig:
    """Read and validate a YAML config; ``None`` loads the embedded default."""
    source = Path(path) if path is not None else DEFAULT_CONFIG
    data = load_yaml(source, "config file")
    return parse_config(data, source)


def config_to_dict(config: RoverConfig) -> dict[str, Any]:
    """Back to the YAML shape (used to hand a config to a subprocess or a ROS parameter)."""
    buses = [{"name": b.name, "interface": b.interface, "channel": b.channel, "bitrate": b.bitrate,
              "kwargs": dict(b.kwargs), "sync_period_ms": s_to_ms(b.sync_period_s),
              "host_node_id": b.host_node_id, "host_heartbeat_ms": s_to_ms(b.host_heartbeat_s),
              "connect_timeout_ms": s_to_ms(b.connect_timeout_s), "sync_timer": b.sync_timer}
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
            "heartbeat_period_ms": s_to_ms(d.heartbeat_period_s),
            "heartbeat_timeout_ms": s_to_ms(d.heartbeat_timeout_s),
            "watchdog_ms": s_to_ms(d.watchdog_s), "arm_on_start": d.arm_on_start,
            "restore_enable_after_reboot": d.restore_enable_after_reboot,
            "homing_method": d.homing_method, "homing_speed_deg_s": d.homing_speed_deg_s,
            "homing_timeout_s": d.homing_timeout_s,
            "identity": {k: v for k, v in vars(d.identity).items() if v is not None},
            "invert": d.invert, "offset_deg": d.offset_deg,
            "quick_stop_deceleration_deg_s2": d.quick_stop_deceleration_deg_s2,
            "host_timeout_ms": s_to_ms(d.host_timeout_s) if d.host_timeout_s is not None else None,
            "on_host_loss": d.on_host_loss, "allow_no_host_watch": d.allow_no_host_watch, "host_watch": d.host_watch,
            "stale_after_syncs": d.stale_after_syncs,
            "sdo_timeout_ms": s_to_ms(d.sdo_timeout_s), "boot_timeout_ms": s_to_ms(d.boot_timeout_s),
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
                               "cmd_timeout_ms": s_to_ms(ds.cmd_timeout_s),
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


# the names callers imported from here before the split (can_config.config stays their door)
__all__ = ["DEFAULT_CONFIG", "GEAR_RATIO_MAX", "GEAR_RATIO_MIN", "GENERIC_EDS", "ON_HOST_LOSS", "BusConfig", "DriveConfig",
           "DriveSystemConfig", "IdentityConfig", "RecorderConfig", "RoverConfig", "SdoSetting", "SimModelConfig",
           "config_to_dict", "load_config", "parse_config", "resolve_eds_path", "resolved", "with_bus_overrides"]
