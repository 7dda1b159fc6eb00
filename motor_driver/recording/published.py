"""What the state topics say of a drive (pure): a MotorState's fields and a /joint_states entry
made from a :class:`~motor_driver.drive.DriveState`. One conversion for the live nodes
(``nodes/joints/messages.py``, ``nodes/rover_driver.py``) and the bus view of recordings and the
Foxglove view (:mod:`motor_driver.recording.busview`), so a recording says what the live topics said.

The rules: a MotorState's angle is wrapped to [0, 360) on a continuous joint (a wheel) and as
measured on a limited one; /joint_states carries the angle as measured (rad, never wrapped: a
wheel's travel), its velocity (rad/s) and torque (Nm). Values whose data is not news by the drive's
verdict (late, lost, re-booting, not configured) are not repeated as if they were: NaN, with
``stale`` and the data's age, and a state that is the verdict's condition (``LATE``, ``LOST``,
``REBOOTING``, ...) rather than the last CiA 402 state read; ``enabled`` is the verdict's usable;
``fault`` is the verdict's ``faulted`` or ``lost`` (the message's definition: Fault or Fault
Reaction Active, or lost), never a flag of the snapshot's (a late drive's last FAULT statusword is
old news, as its angle is). No state of its own.
"""

from __future__ import annotations

import math
import struct
from typing import NamedTuple

from motor_driver.drive.values import DriveState
from motor_driver.drive.verdict import Condition

#: The verdicts a MotorState calls ``fault``.
FAULT_CONDITIONS = frozenset({Condition.FAULTED, Condition.LOST})
#: The largest data age a MotorState carries (a drive never heard: infinite, said as this).
DATA_AGE_MAX_S = 1e9


class MotorStateFields(NamedTuple):
    """rovercan_msgs/MotorState's fields but its header (stamped ``stamp``, frame ``name``)."""

    name: str
    state: str
    angle: float
    velocity: float
    torque: float
    enabled: bool
    fault: bool
    error_code: int
    stale: bool
    data_age: float
    stamp: float


def wrapped_deg(angle_deg: float) -> float:
    """A continuous joint's angle in [0, 360) as MotorState's float32 carries it: a tiny negative
    angle's remainder (360.0 in doubles) and one that float32 rounds up to 360 are 0."""
    angle = angle_deg % 360.0
    return 0.0 if struct.unpack("<f", struct.pack("<f", angle))[0] >= 360.0 else angle


def motor_state_fields(state: DriveState, continuous: bool) -> MotorStateFields:
    """A MotorState of ``state`` (see the module's rules)."""
    angle = wrapped_deg(state.angle_deg) if continuous else state.angle_deg
    verdict = state.verdict
    stale = not verdict.fresh
    return MotorStateFields(
        name=state.name, state=state.state.name if verdict.fresh else verdict.condition.name,
        angle=math.nan if stale else float(angle), velocity=math.nan if stale else float(state.velocity_deg_s),
        torque=math.nan if stale else float(state.torque_nm), enabled=verdict.usable,
        fault=verdict.condition in FAULT_CONDITIONS,
        error_code=state.error_code, stale=stale, data_age=float(min(state.data_age_s, DATA_AGE_MAX_S)),
        stamp=state.stamp)


def joint_entry(state: DriveState) -> tuple[float, float, float]:
    """A drive's /joint_states position (rad), velocity (rad/s) and effort (Nm); NaN where its
    verdict says the data is not news (late, lost, re-booting, not configured)."""
    if not state.verdict.fresh:
        return math.nan, math.nan, math.nan
    return math.radians(state.angle_deg), math.radians(state.velocity_deg_s), state.torque_nm
