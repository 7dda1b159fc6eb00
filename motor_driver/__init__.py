"""CANopen / CiA 402 motor driver (python-can + canopen). Never imports rclpy or virtual_can.

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
from can_config.stop import StopRequested, stop_on_signals
from motor_driver.cia402 import Command, State
from motor_driver.drive import Drive, DriveState, Emcy
from motor_driver.driver import MotorDriver

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
