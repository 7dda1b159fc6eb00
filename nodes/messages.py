"""Driver snapshots into ROS messages, for every node that publishes them."""

from __future__ import annotations

import math

from rovercan_msgs.msg import MotorState

from motor_driver import DriveState


def fill_motor_state(msg: MotorState, state: DriveState, continuous: bool) -> MotorState:
    """Copy a driver snapshot into a MotorState (angle wrapped to [0, 360) on continuous joints;
    NaN values and ``stale`` when no PDO came for ``stale_after_syncs`` SYNC periods)."""
    angle = state.angle_deg % 360.0 if continuous else state.angle_deg
    # stale data is not repeated as if it were news: NaN, with the flag and its age
    msg.angle = math.nan if state.stale else float(angle)
    msg.torque = math.nan if state.stale else float(state.torque_nm)
    msg.velocity = math.nan if state.stale else float(state.velocity_deg_s)
    msg.stale = state.stale
    msg.data_age = float(min(state.data_age_s, 1e9))
    msg.name = state.name
    msg.state = "LOST" if state.lost else state.state.name
    msg.enabled = state.enabled
    msg.fault = state.fault
    msg.error_code = state.error_code
    stamp = state.stamp
    msg.header.stamp.sec = int(stamp)
    msg.header.stamp.nanosec = int((stamp - int(stamp)) * 1e9)
    msg.header.frame_id = state.name
    return msg


__all__ = ["fill_motor_state"]
