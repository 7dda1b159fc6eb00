"""CANopen / CiA 402 motor driver (python-can + canopen). Never imports rclpy or virtual_can.

What lives where:

* :mod:`motor_driver.drive` - one drive, its parts composed (state cache, SDO port, command
  channel, power state machine, limit guard, motion, homing, host watch, boot; :class:`Drive`)
* :mod:`motor_driver.runtime.driver` - every bus and drive of a config: start, safe stop, close
* :mod:`motor_driver.runtime.supervisor`, :mod:`motor_driver.runtime.supervise_bus`, :mod:`motor_driver.runtime.ledger`,
  :mod:`motor_driver.bus.handle`, :mod:`motor_driver.bus.connect`, :mod:`motor_driver.bus.traffic`,
  :mod:`motor_driver.bus.link` - the supervisor's period (the one writer of the runtime state),
  the runtime state and the NMT ledger, one bus, opening a bus, what the bus's traffic shows,
  what the kernel says of the link
* :mod:`motor_driver.bus.sdo_client`, :mod:`motor_driver.protocol.codec`, :mod:`motor_driver.bus.cyclic`,
  :mod:`motor_driver.bus.adapters` - an SDO client that takes only its own answers, the typed codec
  of SDO values, the SYNC on the bus daemon's timer, where a dependency's internals are leaned on
* :mod:`motor_driver.protocol.cia402`, :mod:`motor_driver.protocol.pdo`, :mod:`motor_driver.protocol.units`,
  :mod:`motor_driver.protocol.unit_ranges`, :mod:`motor_driver.protocol.safety` - pure rules: state machine, PDO plan, units and their
  plausible ranges, the safety judgement
* :mod:`motor_driver.runtime.health`, :mod:`motor_driver.bus.load` - pure judgements for the nodes and the
  CLI: a drive's health, the bus load a config makes
* :mod:`motor_driver.rover` - the rover's kinematics and odometry (pure; the drive system feeds them)
* :mod:`motor_driver.recording` - the flight recorder, CAN recordings read back, and the bus as
  ROS 2 messages (no rclpy) for MCAP files and the live Foxglove view
* :mod:`motor_driver.runtime` - the driver at run time: start, supervise, stop; the runtime state
* :mod:`motor_driver.bus` - one CAN bus: opening it, its network and SYNC, its traffic and link
* :mod:`motor_driver.protocol` - CANopen and CiA 402 as pure rules and codecs
* :mod:`motor_driver.process` - a process's life: stop on signals, the heap settled once built,
  repeated log lines at a bounded rate

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
    CommandWouldWait,
    DriveStateError,
    DriveTimeoutError,
    ForeignMasterError,
    MotorError,
    RovercanError,
    SdoError,
    SdoTimeoutError,
)
from motor_driver.drive import Drive, DriveState, Emcy
from motor_driver.process.stop import StopRequested, stop_on_signals
from motor_driver.protocol.cia402 import Command, State
from motor_driver.runtime.driver import MotorDriver

__all__ = [
    "BootError",
    "BusLostError",
    "Command",
    "CommandRejected",
    "CommandWouldWait",
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
