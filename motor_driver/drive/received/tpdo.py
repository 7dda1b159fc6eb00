"""One TPDO's values into what the drive said last (pure but for the position filter it is
handed): the state cache decodes every TPDO with it on the bus's receive thread, and the bus
view (:mod:`motor_driver.recording.busview`: recordings, the live Foxglove view) with its own filter on its
feeding thread, so a recording says what the driver heard.

Owner: the caller's thread; the :class:`~motor_driver.drive.received.position.PositionFilter` it passes is
that thread's too.
"""

from __future__ import annotations

from collections.abc import Sequence

from can_config.objects import OD
from motor_driver.drive.received.position import PositionFilter
from motor_driver.drive.values import Received

#: The objects a TPDO carries, read once: an enum member's lookup costs about 0.13 us, and a TPDO
#: would make up to ten, 6,000 TPDOs a second at six drives and 500 Hz
_STATUSWORD, _POSITION, _VELOCITY = OD.STATUSWORD, OD.POSITION_ACTUAL, OD.VELOCITY_ACTUAL
_TORQUE, _MODE = OD.TORQUE_ACTUAL, OD.MODES_OF_OPERATION_DISPLAY

#: What one TPDO leaves: statusword, mode, position (counts), velocity (its 0x606C unit), torque
#: (per mille), and whether a position was taken (a new sample, plausible or confirmed).
Decoded = tuple[int, int, int, int, float, bool]


def decode_tpdo(indexes: Sequence[int], values: Sequence[int], rx: Received, timestamp: float,
                positions: PositionFilter) -> Decoded:
    """The fields of ``rx`` that one TPDO's ``values`` (its mapped objects ``indexes``, unpacked
    by the layout's codec) replace; a position the joint cannot have reached since the last one
    is held back by ``positions`` (judged at the velocity measured before this TPDO)."""
    sw, mode, position, velocity, torque = rx.statusword, rx.mode, rx.position_counts, rx.velocity_counts_s, \
        rx.torque_permille
    took = False
    for index, value in zip(indexes, values, strict=True):
        if index == _STATUSWORD:
            sw = value
        elif index == _POSITION:
            if positions.plausible(value, position, timestamp, rx.velocity_counts_s):  # measured before
                position = value
                took = True
        elif index == _VELOCITY:
            positions.track_accel(value, timestamp)
            velocity = value
        elif index == _TORQUE:
            torque = value
        elif index == _MODE:
            mode = value
    return sw, mode, position, velocity, torque, took
