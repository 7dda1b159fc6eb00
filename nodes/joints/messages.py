"""Driver snapshots into ROS messages, and header stamps, for every node that publishes them.

Owner: none; pure conversions, called on the publishing node's executor thread.
"""

from __future__ import annotations

from typing import Any

from rovercan_msgs.msg import MotorState

from motor_driver import DriveState
from motor_driver.recording.published import motor_state_fields


def stamp_header(msg_header: Any, stamp: float) -> None:
    """Set a std_msgs/Header's stamp to ``stamp`` (seconds)."""
    msg_header.stamp.sec = int(stamp)
    msg_header.stamp.nanosec = int((stamp - int(stamp)) * 1e9)


def fill_motor_state(msg: MotorState, state: DriveState, continuous: bool) -> MotorState:
    """Copy a driver snapshot into a MotorState (:func:`motor_driver.recording.published.motor_state_fields`:
    angle wrapped to [0, 360) on continuous joints; NaN values and ``stale`` when no PDO came for
    ``stale_after_syncs`` SYNC periods)."""
    fields = motor_state_fields(state, continuous)
    msg.angle = fields.angle
    msg.torque = fields.torque
    msg.velocity = fields.velocity
    msg.stale = fields.stale
    msg.data_age = fields.data_age
    msg.name = fields.name
    msg.state = fields.state
    msg.enabled = fields.enabled
    msg.fault = fields.fault
    msg.error_code = fields.error_code
    stamp_header(msg.header, fields.stamp)
    msg.header.frame_id = state.name
    return msg


__all__ = ["fill_motor_state", "stamp_header"]
