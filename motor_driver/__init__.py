"""CANopen / CiA 402 motor driver (python-can + canopen). Never imports rclpy or virtual_can.

What lives where:

* :mod:`motor_driver.drive` - one drive, its parts composed (state cache, SDO port, command
  channel, power state machine, limit guard, motion, homing, host watch, boot; :class:`Drive`)
* :mod:`motor_driver.driver` - every bus and drive of a config: start, safe stop, close
* :mod:`motor_driver.supervisor`, :mod:`motor_driver.supervise_bus`, :mod:`motor_driver.runtime`,
  :mod:`motor_driver.bushandle`, :mod:`motor_driver.connect`, :mod:`motor_driver.traffic`,
  :mod:`motor_driver.bushealth` - the supervisor's period (the one writer of the runtime state),
  the runtime state and the NMT ledger, one bus, opening a bus, what the bus's traffic shows,
  what the kernel says of the link
* :mod:`motor_driver.sdo_client`, :mod:`motor_driver.codec`, :mod:`motor_driver.cyclic`,
  :mod:`motor_driver.adapters` - an SDO client that takes only its own answers, the typed codec
  of SDO values, the SYNC on the bus daemon's timer, where a dependency's internals are leaned on
* :mod:`motor_driver.cia402`, :mod:`motor_driver.pdo`, :mod:`motor_driver.units`,
  :mod:`motor_driver.unit_ranges`, :mod:`motor_driver.safety`, :mod:`motor_driver.setpoint`,
  :mod:`motor_driver.trajectory` - pure rules: state machine, PDO plan, units and their
  plausible ranges, the safety judgement, the set-point handshake, the streamed move's trapezoid
* :mod:`motor_driver.verdict` - one verdict per drive (usable, late, lost, ...), the one judgement
  every consumer reads; :mod:`motor_driver.frameloss` - a drive's frames expected against received
* :mod:`motor_driver.health`, :mod:`motor_driver.skid_steer`, :mod:`motor_driver.odometry`,
  :mod:`motor_driver.busload` - pure judgements for the nodes and the CLI: a drive's health, the
  drive system's kinematics and odometry, the bus load a config makes
* :mod:`motor_driver.recorder` - the flight recorder, and reading its incidents and CAN
  recordings back; :mod:`motor_driver.errorframes` - SocketCAN error frames decoded;
  :mod:`motor_driver.busview`, :mod:`motor_driver.ros2defs`, :mod:`motor_driver.mcap_out` - the
  bus as ROS 2 messages (no rclpy), for MCAP files and the live Foxglove view
* :mod:`motor_driver.stop`, :mod:`motor_driver.heap`, :mod:`motor_driver.ratelimit` - a
  process's life: stop on signals, the heap settled once built, repeated log lines at a bounded
  rate (used by the driver, the nodes and the CLI; the simulator needs none of them, so they are
  here and not in ``can_config``)

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
from motor_driver.cia402 import Command, State
from motor_driver.drive import Drive, DriveState, Emcy
from motor_driver.driver import MotorDriver
from motor_driver.stop import StopRequested, stop_on_signals

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
