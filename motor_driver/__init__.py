"""CANopen / CiA 402 motor driver (python-can + canopen). Never imports rclpy or virtual_can.

What lives where, in the order the folders build on each other (a folder imports only those
before it; tests/test_module_maps.py holds the order), with the thread that owns each one's state:

* :mod:`motor_driver.process` - a process's life: stop on signals, the heap settled once built,
  repeated log lines at a bounded rate, waits that do not count a hold of the process, background
  jobs supervised (owner: the calling thread; a job's, its worker)
* :mod:`motor_driver.protocol` - CANopen and CiA 402 as pure rules and codecs: the state machine,
  the PDO plan, SDO values, units and their plausible ranges, the host-loss safety judgement,
  SocketCAN error frames (owner: none, pure)
* :mod:`motor_driver.rover` - the rover's kinematics and odometry (pure; the drive system's
  thread feeds them)
* :mod:`motor_driver.bus` - one CAN bus: opening it, its network, SYNC and worker, its traffic and
  the kernel's view of its link, its load, an SDO client, and every reach into a dependency's
  internals (owner: the bus's receive thread feeds its traffic; its worker runs blocking jobs)
* :mod:`motor_driver.drive` - one drive, its parts composed by :class:`Drive`, a room per thread
  that owns state: what the receive thread owns (``received``), what the command channel owns
  (``command``), what the bus's worker owns while the drive boots (``setup``); its face at the
  top (the verdict, the values, the facade)
* :mod:`motor_driver.diagnostics` - drives graded by their verdict, buses and background jobs
  graded, frames lost measured (owner: none, pure; the publishing thread calls it)
* :mod:`motor_driver.follow` - a joint trajectory (FollowJointTrajectory) followed by a group of
  joints on their bus's SYNC clock, and its spline (owner: each group's thread)
* :mod:`motor_driver.recording` - the flight recorder, CAN recordings read back, and the bus as
  ROS 2 messages (no rclpy) for MCAP files and the live Foxglove view (owner: the recorder's
  writer thread; the rest the caller's)
* :mod:`motor_driver.runtime` - the driver at run time: every bus and drive of a config started,
  supervised and stopped (owner: the supervisor thread alone writes the ledger's records)

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
from motor_driver.runtime.driver import MotorDriver, StopReport

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
    "StopReport",
    "StopRequested",
    "stop_on_signals",
]
