"""CANopen / CiA 402 motor driver (python-can + canopen). Never imports rclpy or virtual_can.

What lives where:

* :mod:`motor_driver.drive` - one drive, its parts composed (state cache, SDO port, command
  channel, power state machine, limit guard, motion, homing, host watch, boot; :class:`Drive`)
* :mod:`motor_driver.driver` - every bus and drive of a config: start, safe stop, close
* :mod:`motor_driver.supervisor`, :mod:`motor_driver.supervise_bus`, :mod:`motor_driver.runtime`,
  :mod:`motor_driver.bushandle`, :mod:`motor_driver.connect`, :mod:`motor_driver.traffic` - the
  supervisor's period (the one writer of the runtime state), the runtime state and the NMT
  ledger, one bus, opening a bus, what the bus shows
* :mod:`motor_driver.cia402`, :mod:`motor_driver.pdo`, :mod:`motor_driver.units`,
  :mod:`motor_driver.safety`, :mod:`motor_driver.setpoint` - pure rules: state machine, PDO
  plan, units, the safety judgement, the set-point handshake
* :mod:`motor_driver.recorder`, :mod:`motor_driver.health`, :mod:`motor_driver.cyclic`,
  :mod:`motor_driver.skid_steer`, :mod:`motor_driver.busload`, :mod:`motor_driver.adapters`

    from can_config import load_config
    from motor_driver import MotorDriver, stop_on_signals

    with stop_on_signals(), MotorDriver(load_config()).start() as driver:
        joint = driver.drive("motor")
        joint.enable()
        joint.move_to(90.0, wait=True)
        print(joint.snapshot())
"""

from can_config.errors import (
    BootError,
    BusLostError,
    CommandRejected,
    DriveStateError,
    DriveTimeoutError,
    ForeignMasterError,
    MotorError,
    RovercanError,
    SdoError,
    SdoTimeoutError,
)
from motor_driver.cia402 import Command, State
from motor_driver.drive import Drive, DriveState, Emcy
from motor_driver.driver import MotorDriver
from motor_driver.stop import StopRequested, stop_on_signals

__all__ = [
    "BootError",
    "BusLostError",
    "Command",
    "CommandRejected",
    "Drive",
    "DriveState",
    "DriveStateError",
    "DriveTimeoutError",
    "Emcy",
    "ForeignMasterError",
    "MotorDriver",
    "MotorError",
    "RovercanError",
    "SdoError",
    "SdoTimeoutError",
    "State",
    "StopRequested",
    "stop_on_signals",
]
