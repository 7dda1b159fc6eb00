"""The position filter of one drive: which position samples to believe, and how fast the joint
speeds up.

Owner: the bus's receive thread (the state cache calls it for each position and velocity
sample; the bus view has one of its own, on its feeding thread); boot sets its speed bound from
the drive's units (:meth:`set_units`, drive not booted)
and homing tells it to take the next position as it comes (:meth:`trust_next`).
"""

from __future__ import annotations

import logging

from motor_driver.drive.constants import JUMP_CONFIRMATIONS, MAX_ACCEL_GAP_S, MEASURED_SPEED_CAP
from motor_driver.protocol.units import Scale

logger = logging.getLogger(__name__)

#: The position actual value (0x6064) is an INTEGER32: its counter wraps from 2**31 - 1 to -2**31.
_FULL_RANGE = 1 << 32
_HALF_RANGE = 1 << 31


class PositionFilter:
    """Holds back a position the joint cannot have reached; tracks the velocity's slope."""

    def __init__(self, node_id: int, sync_period_s: float) -> None:
        self._node_id = node_id
        self._sync_period_s = sync_period_s
        self._max_counts_s = 1
        self._counts_per_velocity_unit = 1.0  # position counts per second in one unit of 0x606C
        self._jump_margin_counts = 4.0
        self._last_t = 0.0
        self._suspect: tuple[int, int] | None = None  # (value, samples agreeing since)
        self.implausible = 0
        #: the position reference: counted up whenever a sample is taken that need not follow from the
        #: one before (the first after boot or homing, a confirmed jump such as a reboot's): positions of
        #: two references are never subtracted (odometry, motor_driver/rover/odometry.py)
        self.reference = 0
        self.accel_counts_s2 = 0.0
        self._accel_from = (0, 0.0)

    def set_bound(self, max_counts_s: int, counts_per_deg: float, counts_per_velocity_unit: float = 1.0) -> None:
        """The fastest the joint can go (counts/s), one degree as the margin of a jump, and what
        one unit of the drive's velocity (0x606C, its 0x60A9 unit) is in position counts/s."""
        self._max_counts_s = max_counts_s or 1
        self._jump_margin_counts = max(4.0, counts_per_deg)
        self._counts_per_velocity_unit = counts_per_velocity_unit

    def set_units(self, scale: Scale, max_velocity_deg_s: float) -> None:
        """The bound of :meth:`set_bound` from a drive's units and its joint's top speed."""
        self.set_bound(int(abs(scale.counts_per_deg * max_velocity_deg_s)), scale.counts_per_deg,
                       abs(scale.counts_s_to_deg_s(1.0) * scale.counts_per_deg))

    def trust_next(self) -> None:
        """The next position is taken as it comes (after boot's SDO read, after homing)."""
        self._last_t = 0.0

    def plausible(self, value: int, last: int, timestamp: float, velocity: int = 0) -> bool:
        """Reject a position the joint cannot have reached since the last one (a corrupted or
        foreign frame), unless JUMP_CONFIRMATIONS further samples agree with it (homing, a
        reboot, a real jump). "Cannot" is judged at the faster of the joint's limit and the
        velocity the drive measured before (``velocity``, in its 0x606C unit), up to
        MEASURED_SPEED_CAP times the limit: a shaft coasting past the limit (after a torque
        command) moves that far, and holding its position back would repeat a stale one."""
        last_t = self._last_t
        self._last_t = timestamp
        if not last_t:
            self.reference += 1
            return True
        measured = abs(velocity) * self._counts_per_velocity_unit
        speed = min(max(self._max_counts_s, measured), MEASURED_SPEED_CAP * self._max_counts_s)
        limit = speed * 2.0 * max(timestamp - last_t, 0.001) + self._jump_margin_counts
        if abs(value - last) <= limit:
            self._suspect = None
            return True
        if abs((value - last + _HALF_RANGE) % _FULL_RANGE - _HALF_RANGE) <= limit:
            # the drive's 32-bit position counter wrapped (a continuous joint turning on: 6.6 km of a
            # 0.1 m wheel at 204,800 counts a turn): a step, taken at once, in a new reference (the
            # odometry never subtracts across it), not a jump held back with the old value repeated
            self._suspect = None
            self.reference += 1
            return True
        suspect = self._suspect
        if suspect is not None and abs(value - suspect[0]) <= limit:
            if suspect[1] + 1 >= JUMP_CONFIRMATIONS:
                self._suspect = None
                self.reference += 1
                return True  # confirmed
            self._suspect = (value, suspect[1] + 1)
            return False
        self._suspect = (value, 0)
        self.implausible += 1
        logger.debug("node %d: position %d implausible after %d; held for confirmation", self._node_id, value, last)
        return False

    def track_accel(self, velocity_counts_s: int, timestamp: float) -> None:
        """The slope from the last sample at least half a SYNC period older (two frames that
        queued up and arrive together give no slope of their own)."""
        before, t_before = self._accel_from
        gap = timestamp - t_before
        if 0.0 <= gap < 0.5 * self._sync_period_s:
            return
        self.accel_counts_s2 = (velocity_counts_s - before) / gap if 0.0 < gap <= MAX_ACCEL_GAP_S else 0.0
        self._accel_from = (velocity_counts_s, timestamp)
