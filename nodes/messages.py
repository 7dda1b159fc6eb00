"""Driver snapshots into ROS messages, for every node that publishes them."""

from __future__ import annotations

import math

from rovercan_msgs.msg import MotorState

from motor_driver import DriveState
from motor_driver.verdict import Condition


def fill_motor_state(msg: MotorState, state: DriveState, continuous: bool) -> MotorState:
    """Copy a driver snapshot into a MotorState (angle wrapped to [0, 360) on continuous joints),
    as its verdict says: values whose data is not news (late, lost, re-booting, not configured)
    are NaN with ``stale`` and their age; ``enabled`` is usable."""
    verdict = state.verdict
    known = verdict.fresh
    angle = state.angle_deg % 360.0 if continuous else state.angle_deg
    msg.angle = float(angle) if known else math.nan
    msg.torque = float(state.torque_nm) if known else math.nan
    msg.velocity = float(state.velocity_deg_s) if known else math.nan
    msg.stale = not known
    msg.data_age = float(min(state.data_age_s, 1e9))
    msg.name = state.name
    msg.state = "LOST" if verdict.condition is Condition.LOST else state.state.name
    msg.enabled = verdict.usable
    msg.fault = state.fault
    msg.error_code = state.error_code
    stamp = state.stamp
    msg.header.stamp.sec = int(stamp)
    msg.header.stamp.nanosec = int((stamp - int(stamp)) * 1e9)
    msg.header.frame_id = state.name
    return msg


__all__ = ["fill_motor_state"]
