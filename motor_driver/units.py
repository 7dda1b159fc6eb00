"""Engineering units at the API (degrees, deg/s, Nm), drive units on the wire (pure).

Position: encoder counts. ``counts_per_deg = counts_per_rev x gear_ratio / 360`` (counts per
motor revolution, motor revolutions per joint revolution). Velocity: counts/s. Torque:
per mille of the motor's rated torque (0x6077 / 0x6071); joint torque = motor torque x gear.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from can_config.errors import CommandRejected

INT32_MIN = -(2**31)
INT32_MAX = 2**31 - 1


@dataclass(frozen=True)
class Scale:
    counts_per_deg: float
    rated_torque_nm: float
    gear_ratio: float = 1.0

    def deg_to_counts(self, angle_deg: float) -> int:
        return int(round(angle_deg * self.counts_per_deg))

    def counts_to_deg(self, counts: float) -> float:
        return counts / self.counts_per_deg

    def deg_s_to_counts_s(self, velocity_deg_s: float) -> int:
        return int(round(velocity_deg_s * self.counts_per_deg))

    def counts_s_to_deg_s(self, counts_s: float) -> float:
        return counts_s / self.counts_per_deg

    def permille_to_nm(self, permille: float) -> float:
        return permille / 1000.0 * self.rated_torque_nm * self.gear_ratio

    def nm_to_permille(self, torque_nm: float) -> int:
        return int(round(torque_nm / (self.rated_torque_nm * self.gear_ratio) * 1000.0))


def require_finite(name: str, value: float, unit: str) -> float:
    """Refuse NaN and infinities with an error naming the input."""
    if not isinstance(value, (int, float)) or isinstance(value, bool) or not math.isfinite(value):
        raise CommandRejected(f"{name}={value!r} {unit}: not a finite number; send a real value."
                              " Nothing was sent to the drive.")
    return float(value)


def nearest_equivalent(command_deg: float, current_deg: float) -> float:
    """For a continuous joint: the angle equal to ``command_deg`` modulo 360 that is closest to
    ``current_deg`` (multi-turn), so 359.9 -> 0.0 moves +0.1 degree, not -359.9."""
    delta = (command_deg - current_deg + 180.0) % 360.0 - 180.0
    return current_deg + delta


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
