"""Engineering units at the API (degrees, deg/s, Nm), drive units on the wire (pure).

Position: encoder counts. ``counts_per_deg = counts_per_rev x gear_ratio / 360`` (counts per
motor revolution, motor revolutions per joint revolution). Velocity: counts/s. Torque:
per mille of the motor's rated torque (0x6077 / 0x6071); joint torque = motor torque x gear.

Polarity and offset (a mirrored wheel, a joint whose zero is not the drive's): the joint angle
is ``offset_deg + sign x drive angle`` with ``sign = -1`` for an inverted joint; velocities
and torques carry the sign. Every conversion of a position, velocity or torque goes through
the signed methods here, so commands, readings and limits agree; the unsigned
``*_magnitude`` methods are for profile speeds and accelerations, which have no direction.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from can_config.errors import CommandRejected
from motor_driver.protocol.unit_ranges import check_unit_objects, check_units_per_deg, si_parts

#: Degrees in a radian: ROS speaks radians, the driver's API degrees.
DEG_PER_RAD = 180.0 / math.pi

INT32_MIN = -(2**31)
INT32_MAX = 2**31 - 1


@dataclass(frozen=True)
class Scale:
    """Drive units <-> joint units. ``counts_per_deg``: position units per joint degree;
    ``velocity_units_per_deg_s``: velocity units (0x606C/0x60FF/0x6081) per joint deg/s;
    accelerations are velocity units per second."""

    counts_per_deg: float
    rated_torque_nm: float
    gear_ratio: float = 1.0
    velocity_units_per_deg_s: float = 0.0  # 0: the same as counts_per_deg (increments/s)
    invert: bool = False
    offset_deg: float = 0.0
    #: acceleration units (0x6083/0x6084/0x6085) per joint deg/s^2; 0: velocity units per second
    acceleration_units_per_deg_s2: float = 0.0
    #: False when neither the config (counts_per_rev) nor the drive (0x608F, 0x60A8, 0x6092) gave
    #: the position resolution: the figures above are an assumption, and no motion is commanded
    resolution_known: bool = True

    @property
    def _v(self) -> float:
        return self.velocity_units_per_deg_s or self.counts_per_deg

    @property
    def sign(self) -> int:
        return -1 if self.invert else 1

    def deg_to_counts(self, angle_deg: float) -> int:
        """Joint angle -> drive position."""
        return int(round(self.sign * (angle_deg - self.offset_deg) * self.counts_per_deg))

    def counts_to_deg(self, counts: float) -> float:
        """Drive position -> joint angle."""
        return self.offset_deg + self.sign * counts / self.counts_per_deg

    def span_deg(self, counts: float) -> float:
        """A distance in drive counts as joint degrees (no sign, no offset)."""
        return abs(counts) / self.counts_per_deg

    def deg_s_to_counts_s(self, velocity_deg_s: float) -> int:
        """Joint velocity -> drive velocity units (signed)."""
        return int(round(self.sign * velocity_deg_s * self._v))

    def counts_s_to_deg_s(self, counts_s: float) -> float:
        """Drive velocity units -> joint velocity (signed)."""
        return self.sign * counts_s / self._v

    def magnitude_to_drive(self, per_s: float) -> int:
        """A speed (deg/s, no direction) in drive units."""
        return int(round(abs(per_s) * self._v))

    def acceleration_to_drive(self, deg_s2: float) -> int:
        """An acceleration (deg/s^2, no direction) in drive units (0x60AA, else velocity units/s)."""
        return int(round(abs(deg_s2) * (self.acceleration_units_per_deg_s2 or self._v)))

    def permille_to_nm(self, permille: float) -> float:
        return self.sign * permille / 1000.0 * self.rated_torque_nm * self.gear_ratio

    def nm_to_permille(self, torque_nm: float) -> int:
        return int(round(self.sign * torque_nm / (self.rated_torque_nm * self.gear_ratio) * 1000.0))

    def limits_to_counts(self, min_deg: float, max_deg: float) -> tuple[int, int]:
        """Joint limits as the drive's (low, high) position limits (0x607D), through polarity."""
        a, b = self.deg_to_counts(min_deg), self.deg_to_counts(max_deg)
        return min(a, b), max(a, b)


def require_finite(name: str, value: float, unit: str) -> float:
    """Refuse NaN and infinities with an error naming the input."""
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
        raise CommandRejected(f"{name}={value!r} {unit}: not a finite number; send a real value."
                              " Nothing was sent to the drive.")
    return float(value)


def shortest_delta_deg(delta_deg: float) -> float:
    """An angle difference the short way round, in [-180, 180): 359.9 -> -0.1."""
    return (delta_deg + 180.0) % 360.0 - 180.0


def nearest_equivalent(command_deg: float, current_deg: float) -> float:
    """For a continuous joint: the angle equal to ``command_deg`` modulo 360 that is closest to
    ``current_deg`` (multi-turn), so 359.9 -> 0.0 moves +0.1 degree, not -359.9."""
    return current_deg + shortest_delta_deg(command_deg - current_deg)


def check_limits(name: str, angle_deg: float, min_deg: float | None, max_deg: float | None) -> None:
    if min_deg is not None and angle_deg < min_deg:
        raise CommandRejected(f"{name}: {angle_deg:g} deg is below the lower limit min_deg="
                              f"{min_deg:g} (allowed {min_deg:g} to {max_deg:g} deg). Nothing was sent.")
    if max_deg is not None and angle_deg > max_deg:
        raise CommandRejected(f"{name}: {angle_deg:g} deg is above the upper limit max_deg="
                              f"{max_deg:g} (allowed {min_deg:g} to {max_deg:g} deg). Nothing was sent.")


def check_counts(name: str, counts: int, what: str) -> int:
    if not INT32_MIN <= counts <= INT32_MAX:
        raise CommandRejected(f"{name}: {what} of {counts} counts does not fit the drive's 32-bit"
                              " range; command a smaller value.")
    return counts


# SI unit codes (CiA 402 / CiA 303-2) in 0x60A8-0x60AA: prefix << 24 | numerator << 16 | denominator << 8
SI_REVOLUTION = 0xB4
SI_INCREMENT = 0xB5
SI_SECOND = 0x03
SI_MINUTE = 0x47
SI_SECOND_SQUARED = 0x57
#: Used when neither the config nor the drive gives the position resolution (read-only use).
ASSUMED_COUNTS_PER_REV = 4096

#: The drive objects a scale is derived from: (index, sub-indexes). All UNSIGNED32 (CiA 402),
#: so they are decoded without an EDS: they are read from every drive, whatever its EDS lists.
UNIT_OBJECTS: tuple[tuple[int, tuple[int, ...]], ...] = (
    (0x608F, (1, 2)), (0x6091, (1, 2)), (0x6092, (1, 2)), (0x60A8, (0,)), (0x60A9, (0,)), (0x60AA, (0,)),
    (0x6076, (0,)))


_UNIT_KEYS = frozenset((index, sub) for index, subs in UNIT_OBJECTS for sub in subs)
_SDO_UPLOAD_REPLY, _SDO_ABORT = 2, 4


def unit_object_answer(data: bytes) -> tuple[tuple[int, int], int | None] | None:
    """A drive's SDO answer (its frame 0x580 + node) to the read of one of :data:`UNIT_OBJECTS`,
    as the driver's boot reads them, seen on the bus: ((index, sub), value) for an expedited
    upload (decoded as :func:`read_unit_objects` does), ((index, sub), None) for an abort (no such
    object); None for any other frame."""
    if len(data) < 4:
        return None
    key = (int.from_bytes(data[1:3], "little"), data[3])
    if key not in _UNIT_KEYS:
        return None
    command = data[0] >> 5
    if command == _SDO_ABORT:
        return key, None
    if command != _SDO_UPLOAD_REPLY or not data[0] & 0x02 or len(data) < 8:
        return None
    unused = (data[0] >> 2) & 3 if data[0] & 1 else 0
    return key, int.from_bytes(data[4:8 - unused], "little")


def read_unit_objects(upload: Callable[[int, int], bytes | None]) -> dict[tuple[int, int], int]:
    """The unit objects a drive has, decoded as UNSIGNED32. ``upload(index, sub)`` reads one by
    SDO and returns None where the drive answers that it has no such object (an abort); the
    same reader serves the driver and the bench, so both derive the same scale."""
    objects: dict[tuple[int, int], int] = {}
    for index, subs in UNIT_OBJECTS:
        for sub in subs:
            raw = upload(index, sub)
            if raw:
                objects[(index, sub)] = int.from_bytes(raw[:4].ljust(4, b"\0"), "little")
    return objects


def _ratio(objects: dict[tuple[int, int], int], index: int) -> float | None:
    num, den = objects.get((index, 1)), objects.get((index, 2))
    if not num or not den:
        return None
    return num / den


def scale_from_objects(counts_per_rev: int | None, gear_ratio: float, rated_torque_nm: float,
                       objects: dict[tuple[int, int], int], *, invert: bool = False,
                       offset_deg: float = 0.0) -> tuple[Scale, list[str]]:
    """The scale of a drive from its own objects where it provides them, else from the config.

    ``objects`` holds what the drive reported (:func:`read_unit_objects`): 0x608F (encoder
    increments per motor rev), 0x6091 (motor revs per shaft rev), 0x6092 (feed per shaft rev),
    0x60A8/0x60A9/0x60AA (SI units of position, velocity, acceleration), 0x6076 (rated torque,
    mNm). Rule: with a feed constant other than 1:1 the drive reports position in feed units
    (feed per joint revolution); a position unit of 10^p revolutions gives 10^-p units per motor
    revolution; otherwise increments, with 0x608F (when not 1:1) as increments per motor
    revolution, else the config's ``counts_per_rev``. Where none of these says it, the scale
    assumes ASSUMED_COUNTS_PER_REV and ``resolution_known`` is False: nothing may move on it.
    Returns the scale and notes on what came from where.
    """
    check_unit_objects(objects)
    notes: list[str] = []
    enc = _ratio(objects, 0x608F)
    gear_obj = _ratio(objects, 0x6091)
    feed = _ratio(objects, 0x6092)
    gear = gear_ratio
    known = True
    if gear_obj is not None and gear_obj != 1.0:
        if gear_obj != gear_ratio:
            notes.append(f"gear ratio {gear_obj:g} from 0x6091 (config says {gear_ratio:g})")
        gear = gear_obj
    position_si = objects.get((0x60A8, 0))
    p_prefix, p_num, _ = si_parts(position_si) if position_si else (0, SI_INCREMENT, 0)
    if feed is not None and feed != 1.0:
        units_per_joint_rev = feed
        notes.append(f"position in feed units: {feed:g} per joint revolution (0x6092)")
    elif p_num == SI_REVOLUTION:
        units_per_joint_rev = 10.0 ** -p_prefix * gear
        notes.append(f"position in 10^{p_prefix} motor revolutions (0x60A8)")
    else:
        if enc is not None and enc != 1.0:
            if counts_per_rev is not None and counts_per_rev != enc:
                notes.append(f"encoder {enc:g} increments/rev from 0x608F (config says {counts_per_rev})")
            motor_counts = enc
        elif counts_per_rev is not None:
            motor_counts = float(counts_per_rev)
        else:
            known = False
            motor_counts = float(ASSUMED_COUNTS_PER_REV)
            notes.append(f"position resolution unknown: no counts_per_rev in the config and no 0x608F/0x60A8 on"
                         f" the drive; readings assume {ASSUMED_COUNTS_PER_REV} counts/rev and motion is refused")
        units_per_joint_rev = motor_counts * gear
    counts_per_deg = units_per_joint_rev / 360.0
    velocity = _per_unit(objects, 0x60A9, "velocity", gear, counts_per_deg, notes)
    acceleration = _per_unit(objects, 0x60AA, "acceleration", gear, counts_per_deg, notes)
    check_units_per_deg(position=counts_per_deg, velocity=velocity, acceleration=acceleration)
    rated = rated_torque_nm
    mnm = objects.get((0x6076, 0))
    if mnm:
        rated = mnm / 1000.0
        if abs(rated - rated_torque_nm) > 1e-9:
            notes.append(f"rated torque {rated:g} Nm from 0x6076 (config says {rated_torque_nm:g})")
    return Scale(counts_per_deg, rated, gear, velocity, invert, offset_deg, acceleration, known), notes


#: The time units of 0x60A9 (velocity) and 0x60AA (acceleration) this driver reads: SI
#: denominator -> (seconds per that unit, its name in a note).
_PER_TIME: dict[int, dict[int, tuple[float, str]]] = {
    0x60A9: {SI_SECOND: (1.0, "s"), SI_MINUTE: (60.0, "min")},
    0x60AA: {SI_SECOND_SQUARED: (1.0, "s^2")},
}


def _per_unit(objects: dict[tuple[int, int], int], index: int, what: str, gear: float, counts_per_deg: float,
              notes: list[str]) -> float:
    """Joint deg/s (0x60A9, velocity) or deg/s^2 (0x60AA, acceleration) per unit of the drive's
    ``what``, or 0.0 where it does not say."""
    si = objects.get((index, 0))
    if not si:
        return 0.0
    prefix, numerator, denominator = si_parts(si)
    per = _PER_TIME[index].get(denominator)
    if per is None:
        return 0.0
    seconds, unit = per
    if numerator == SI_REVOLUTION:
        # value x 10^prefix motor revolutions per (s|min|s^2) -> joint deg/s (deg/s^2)
        notes.append(f"{what} in 10^{prefix} rev/{unit} (0x{index:04X})")
        return seconds / (10.0**prefix * 360.0 / gear)
    if numerator == SI_INCREMENT:
        return counts_per_deg * seconds / 10.0**prefix
    return 0.0
