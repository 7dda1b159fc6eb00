"""Skid-steer odometry from measured wheel motion (pure: no I/O, no ROS; the drive system feeds it).

What it integrates, as ros2_control's diff_drive_controller does with position feedback: each
wheel's own position delta between two of its own samples (the PDO's time, not the caller's
tick). A wheel counts only while its data can be trusted:

* a sample is taken only from a wheel that is fresh, not lost and not faulted (``WheelSample.trusted``);
  a lost or faulted wheel forgets its last sample (``forget``), so its next trusted one starts anew;
  a wheel whose data is only late (stale) adds nothing meanwhile and keeps its last sample: its
  next one, in the same reference, carries the motion the encoder counted over the gap;
* two samples are subtracted only within one position reference (``reference``: boot, homing and a
  reboot's jump start a new one): the first sample of a new reference is never a jump;
* a sample no newer than the last one is no motion (the same PDO read twice).

Each side's distance is the mean of its wheels' deltas since the last step; the body moves by
the midpoint rule. A side with no trusted wheel stops the integration: the pose is kept, the twist
is zero and :attr:`OdometryStep.trusted` is False with the reason, for the caller to publish a
large covariance and say why. Nothing is ever extrapolated from a velocity or a command.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

from motor_driver.skid_steer import Pose2D, Twist2D, integrate

#: the variance published for what is not measured (a planar robot's z, roll, pitch; all of it
#: while the odometry stands still for want of trusted wheels)
UNKNOWN_VARIANCE = 1.0e6


@dataclass(frozen=True)
class WheelSample:
    """One wheel's newest position as the driver received it."""

    angle_rad: float
    stamp: float  # the time of the PDO that carried it (s)
    reference: int  # the position reference it belongs to
    trusted: bool = True
    why_not: str = ""  # the reason it is not trusted, for diagnostics ("stale for 120 ms")
    forget: bool = False  # untrusted and its last sample no longer to be followed (lost, faulted)
    velocity_rad_s: float = 0.0  # the drive's own velocity actual value, sent with the position


@dataclass(frozen=True)
class OdometryStep:
    pose: Pose2D
    twist: Twist2D  # measured: the trusted wheels' own velocity actual values; zero when untrusted
    trusted: bool
    why_not: str = ""  # which side has no trusted wheel, and why each of its wheels is out


class WheelOdometry:
    """Pose from the wheels of a skid-steer rover; one instance, called from one thread."""

    def __init__(self, left: Sequence[str], right: Sequence[str], track_width_m: float,
                 wheel_radius_m: float) -> None:
        if not left or not right:
            raise ValueError("odometry needs at least one wheel on each side")
        self.left, self.right = tuple(left), tuple(right)
        self.track_width_m = track_width_m
        self.wheel_radius_m = wheel_radius_m
        self.pose = Pose2D()
        self._last: dict[str, WheelSample] = {}

    def reset(self, pose: Pose2D | None = None) -> None:
        """Start again at ``pose`` (the origin by default), every wheel's reference forgotten."""
        self.pose = pose or Pose2D()
        self._last.clear()

    def _delta(self, name: str, sample: WheelSample | None) -> float | None:
        """Radians turned since this wheel's last sample (0.0: nothing new), or None where it
        counts for nothing; the new sample becomes the last one."""
        last = self._last.get(name)
        if sample is None or not sample.trusted or not math.isfinite(sample.angle_rad):
            if sample is None or sample.forget or not math.isfinite(sample.angle_rad):
                self._last.pop(name, None)
            return None
        if last is not None and sample.stamp <= last.stamp:
            return 0.0  # nothing new: no motion, still trusted
        self._last[name] = sample
        if last is None or last.reference != sample.reference:
            return None  # a new reference starts here
        return sample.angle_rad - last.angle_rad

    def _side(self, names: tuple[str, ...], samples: Mapping[str, WheelSample]) -> tuple[float, float, int]:
        """(mean distance m, mean rim speed m/s, wheels that count) of one side. A wheel with no
        new sample counts as no motion: a side's mean over a fixed set of wheels adds up to the
        mean of their whole travel, whichever step each delta lands in. The speed is the trusted
        wheels' own velocity actual values (a PDO that carries no position makes no delta of
        its own time)."""
        distance = 0.0
        counted = 0
        speeds = []
        for name in names:
            sample = samples.get(name)
            turned = self._delta(name, sample)
            if sample is not None and sample.trusted and math.isfinite(sample.velocity_rad_s):
                speeds.append(sample.velocity_rad_s * self.wheel_radius_m)
            if turned is None:
                continue
            counted += 1
            distance += turned * self.wheel_radius_m
        if not counted:
            return 0.0, 0.0, 0
        return distance / counted, sum(speeds) / len(speeds) if speeds else 0.0, counted

    def step(self, samples: Mapping[str, WheelSample]) -> OdometryStep:
        """Integrate what the wheels measured since the last step."""
        left_m, left_m_s, left_n = self._side(self.left, samples)
        right_m, right_m_s, right_n = self._side(self.right, samples)
        if not left_n or not right_n:
            side = "left" if not left_n else "right"
            wheels = self.left if not left_n else self.right
            reasons = ", ".join(f"{n} {self._why(samples.get(n))}" for n in wheels)
            return OdometryStep(self.pose, Twist2D(), False,
                                f"odometry stopped: no trusted wheel on the {side} side ({reasons})")
        forward = (left_m + right_m) / 2.0
        turn = (right_m - left_m) / self.track_width_m
        self.pose = integrate(self.pose, Twist2D(forward, turn), 1.0)  # distances: one unit of "time"
        twist = Twist2D((left_m_s + right_m_s) / 2.0, (right_m_s - left_m_s) / self.track_width_m)
        return OdometryStep(self.pose, twist, True)

    def _why(self, sample: WheelSample | None) -> str:
        if sample is None:
            return "not sampled"
        if not sample.trusted:
            return sample.why_not or "not trusted"
        return "starting a new position reference"


def yaw_from_wheels(left_rad: Sequence[float], right_rad: Sequence[float], track_width_m: float,
                    wheel_radius_m: float) -> float:
    """The heading change a skid-steer rover's wheel turns imply (rad): the mean right-side rim
    travel minus the left's over the track width. For tests and bench checks of the odometry."""
    left_m = sum(left_rad) / len(left_rad) * wheel_radius_m
    right_m = sum(right_rad) / len(right_rad) * wheel_radius_m
    return (right_m - left_m) / track_width_m
