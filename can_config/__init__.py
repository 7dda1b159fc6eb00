"""YAML configuration of buses and drives, EDS handling, and the passive CANopen tables.

Imports neither ``motor_driver`` nor ``virtual_can`` (nor rclpy): both of them, the nodes and
the CLI build on it.

What lives where: :mod:`can_config.model` (the config's dataclasses, each field declaring its
key: :mod:`can_config.keys`), :mod:`can_config.fields` (the checks), :mod:`can_config.config` (parse, load, dump),
:mod:`can_config.reference` (the docs' key reference, generated), :mod:`can_config.eds`,
:mod:`can_config.objects` (CANopen tables), :mod:`can_config.errors` (the exception tree),
:mod:`can_config.recording`, :mod:`can_config.errorframes`, :mod:`can_config.bits`.
"""

from can_config.config import (
    DEFAULT_CONFIG,
    GENERIC_EDS,
    BusConfig,
    DriveConfig,
    DriveSystemConfig,
    IdentityConfig,
    RoverConfig,
    config_to_dict,
    load_config,
    parse_config,
    with_bus_overrides,
)
from can_config.eds import check_cia402, load_drive_od, load_od
from can_config.errors import ConfigError, EdsError, RovercanError

__all__ = [
    "DEFAULT_CONFIG",
    "GENERIC_EDS",
    "BusConfig",
    "ConfigError",
    "DriveConfig",
    "DriveSystemConfig",
    "EdsError",
    "IdentityConfig",
    "RoverConfig",
    "RovercanError",
    "check_cia402",
    "config_to_dict",
    "load_config",
    "load_drive_od",
    "load_od",
    "parse_config",
    "with_bus_overrides",
]
