"""YAML configuration of buses and drives, EDS handling, and the passive CANopen tables.

Imports neither ``motor_driver`` nor ``virtual_can`` (nor rclpy): both of them, the nodes and
the CLI build on it.

What lives where:

- :mod:`can_config.model`: the config's dataclasses, each field declaring its key
  (:mod:`can_config.keys`); :mod:`can_config.fields`: the checks; :mod:`can_config.config`:
  parse, load, dump; :mod:`can_config.reference`: the docs' key reference, generated
- :mod:`can_config.eds`: EDS files; :mod:`can_config.objects`: the passive CANopen tables
  (object indexes, data types, codes); :mod:`can_config.bits`: the bit timing of a frame
- :mod:`can_config.errors`: the project's one exception tree
- :mod:`can_config.textfile`: reading a text input (size, encoding, YAML without duplicate
  keys): the config's own reader, and the simulator's for its scenarios
- :mod:`can_config.realtime`: SCHED_FIFO for a thread or a process. Not configuration, but
  both the simulator (its SYNC timer thread) and the driver's processes use it, and this is the
  one package both may import (``virtual_can`` never imports ``motor_driver``)

The runtime helpers that only the driver, the nodes or the CLI use live in ``motor_driver``:
signals (:mod:`motor_driver.process.stop`), heap settling (:mod:`motor_driver.process.heap`), rate-limited logs
(:mod:`motor_driver.process.ratelimit`), the SDO value codec (:mod:`motor_driver.protocol.codec`: the simulator
has its own, written from the standard), error frames (:mod:`motor_driver.protocol.errorframes`), CAN
recordings and incident files (:mod:`motor_driver.recording.files`,
:mod:`motor_driver.recording.incident`).
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
    simulated_config,
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
    "simulated_config",
    "with_bus_overrides",
]
