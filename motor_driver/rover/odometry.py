"""Skid-steer odometry from measured wheel motion (pure: no I/O, no ROS; the drive system feeds it).

What it integrates, as ros2_control's diff_drive_controller does with position feedback: each
wheel's own position delta between two of its own samples (ordered by the driver's monotonic
receive time, never the frame's wall clock: a clock step back is not "no motion"; not the
caller's tick). A wheel counts only while its data can be trusted (the caller judges it from the
drive's verdict, ``nodes/rover/wheels.py``).

Samples of different buses are paired by the moment they measure, not by the step that reads them:
each step integrates up to one common instant, the oldest newest sample of the wheels that count
(:attr:`OdometryStep.measured_at`), and every wheel's position at that instant is interpolated
between two of its own samples (its position at the last instant and its RAW_SAMPLES newest
samples; never extrapolated). A sample's instant is its bus stamp (a synchronous TPDO's: the SYNC it
answers) on the receive clock, by one offset for every wheel (the least receive-minus-bus-time
difference any wheel shows): a bus whose drives answer their SYNC late is still paired at its SYNCs.
Two buses whose SYNCs are apart (each bus has its own) thus give the heading the wheels had at one
moment: the left side's newest sample is no longer paired with the right side's of a SYNC earlier.
An interpolation error is not lost either: the next step's delta starts from the same interpolated
point, so each wheel's sum of deltas is its own travel.

* a sample is taken only from a wheel that is usable and heard within its PDO period
  (``WheelSample.trusted``); a wheel that cannot count (lost, out, disabled, quick-stopped,
  faulted, re-booting) forgets its last sample (``forget``), so its next trusted one starts anew;
  a wheel whose data is only late (silent for longer than its PDO period, or stale) keeps its last
  sample: while its side's other wheels measure, it is taken to travel as they do, and when it is
  heard again its own delta over the gap settles the difference (a wheel lost meanwhile, or back
  in a new reference, leaves their estimate standing); while its whole side is late, its next
  sample carries the gap (the other side's travel waits for it), for at most MAX_BRIDGED_GAP_S:
  late for longer, its wheels start anew as lost ones do. The travel estimated rather than
  measured, settled or not, is :attr:`OdometryStep.estimated_m`, for the caller's covariance;
* two samples are subtracted only within one position reference (``reference``: boot, homing and a
  reboot's jump start a new one): the first sample of a new reference is never a jump;
* a sample no newer than the last one is no motion (the same PDO read twice); a step whose common
  instant is not newer than the last one integrates nothing and says so (``measured_at`` 0.0: the
  caller publishes nothing measured for it);
* while a side has no trusted wheel nothing is integrated, and the other side's travel is kept to
  be paired with the late side's next sample, or dropped where that side's wheels were lost
  (:meth:`WheelOdometry.step`).

Each side's distance is the mean of its wheels' deltas since the last step; the body moves by
the midpoint rule. A side with no trusted wheel stops the integration: the pose is kept, the twist
is zero and :attr:`OdometryStep.trusted` is False with the reason, for the caller to publish a
large covariance and say why. Nothing is ever extrapolated from a velocity or a command.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from typing import NamedTuple

from motor_driver.rover.skid_steer import Pose2D, Twist2D, integrate

#: A frame's receive time later than its bus stamp by more than this beyond the least seen (or
#: earlier than that least by more): the wall clock stepped (or the process was starved); the
#: alignment starts anew from this frame (s)
CLOCK_STEP_S = 0.2
#: How far the least receive-minus-bus-time offset may rise per step: the wall clock's slew against
#: the monotonic clock (NTP slews at most 0.5 ms/s; 50 steps a second)
OFFSET_DRIFT_S = 1.0e-5

#: The samples of each wheel kept to interpolate its position at a common instant: the instant is
#: the oldest newest sample of all wheels, which on another bus (a longer SYNC period, drives that
#: answer late) may be older than this wheel's previous sample (can1's SYNC every 89 ms answered
#: 30 ms late: up to 119 ms old, against can0's samples every 61 ms); with two, a wheel starting a
#: reference could not start until the two happened to cover it, and a straight line from its last
#: point over an older sample bridged more than one SYNC period
RAW_SAMPLES = 4

#: The longest gap a late side's next sample may bridge (s since the last instant integrated): its
#: travel over the gap and the other side's are one straight step of the midpoint rule, a chord
#: of whatever the rover drove meanwhile (0.5 s at 1.7 rad/s: 3 % short). Late for longer (its
#: SYNC stopped while its heartbeats went on), its wheels are dropped as lost ones are and start
#: anew when heard: the pose does not jump by the chord of a ten-second circle.
MAX_BRIDGED_GAP_S = 0.5

#: the variance published for what is not measured (a planar robot's z, roll, pitch; all of it
#: while the odometry stands still for want of trusted wheels)
UNKNOWN_VARIANCE = 1.0e6


class WheelSample(NamedTuple):
    """One wheel's newest position as the driver received it (a NamedTuple, not a frozen
    dataclass: a dozen are made per odometry step, 50 steps a second; one costs 0.8 us against 2 us,
    a changed copy 0.8 us against 4: docs/performance.md)."""

    angle_rad: float
    stamp: float  # when the driver received the PDO that carried it (monotonic, s)
    reference: int  # the position reference it belongs to
    trusted: bool = True
    why_not: str = ""  # the reason it is not trusted, for diagnostics ("stale for 120 ms")
    forget: bool = False  # untrusted and its last sample no longer to be followed (lost, faulted)
    silent: bool = False  # untrusted only for silence shorter than its staleness bound (a PDO late)
    velocity_rad_s: float = 0.0  # the drive's own velocity actual value, sent with the position
    #: when the frame was on the bus (the bus's or kernel's stamp, wall clock; 0.0 unknown): what
    #: the odometry pairs the buses by, aligned to ``stamp``'s clock (a receive thread's wake-up
    #: varies by milliseconds, the bus's stamp does not)
    bus_stamp: float = 0.0


@dataclass(frozen=True)
class OdometryStep:
    pose: Pose2D
    twist: Twist2D  # measured: the trusted wheels' own velocity actual values; zero when untrusted
    trusted: bool
    why_not: str = ""  # which side has no trusted wheel, and why each of its wheels is out
    #: travel taken to be as the side's other wheels' for wheels not heard (m): not yet settled by
    #: their own samples, or never (they were lost); per wheel, over its side's wheel count
    estimated_m: float = 0.0
    #: the instant (monotonic receive time, s) the pose was measured at, when this step integrated
    #: one; 0.0: nothing new was measured on both sides (the pose is the last step's)
    measured_at: float = 0.0


@dataclass(frozen=True)
class _Update:
    """What a step does to one wheel's last sample."""

    name: str
    sample: WheelSample | None  # the new last sample (None: keep the old one)
    forget: bool  # drop the last sample (lost, faulted)
    restart: bool = False  # ``sample`` starts a new reference (no delta of its own)


@dataclass(frozen=True)
class _Side:
    distance_m: float
    speed_m_s: float
    counted: int
    updates: list[_Update]
    late: list[str]  # wheels only late this step (their last sample kept)


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
        self._twist = Twist2D()
        #: each wheel's position at the last common instant it was counted at (or its first
        #: sample of a reference): where its next delta starts
        self._last: dict[str, WheelSample] = {}
        #: each wheel's RAW_SAMPLES newest trusted samples (newest first), of one reference: what its
        #: position at a common instant is interpolated from
        self._raw: dict[str, tuple[WheelSample, ...]] = {}
        self._received: dict[str, float] = {}  # the receive time of each wheel's newest kept sample
        self._instant = 0.0  # the last common instant integrated (monotonic, s)
        #: the least (receive time - bus stamp) any wheel showed: the bus stamps on the monotonic clock
        #: (one clock for every bus: the host's wall clock its kernel or bus server stamps by)
        self._offset: float | None = None
        #: late wheels' travel already counted as their side's others' (m): taken off their next delta
        self._attributed: dict[str, float] = {}
        self._never_settled_m = 0.0  # estimates of wheels forgotten before they were heard again

    def _align(self, samples: Mapping[str, WheelSample]) -> None:
        """The offset between the bus stamps' clock and the receive times': the least (receive time -
        bus stamp) of the wheels' samples, this step's least and the last (risen by OFFSET_DRIFT_S).
        One for all wheels, never a wheel's own: a wheel (or a whole bus) whose answers come late
        after its SYNC shows its lateness in that difference, and an offset of its own would take the
        lateness for the clocks' and stamp its samples when they came, not when they measured."""
        seen = [s.stamp - s.bus_stamp for s in samples.values() if s.trusted and s.bus_stamp]
        if not seen:
            return
        least, offset = min(seen), self._offset
        if offset is None or abs(least - offset) > CLOCK_STEP_S:
            self._offset = least
        else:
            self._offset = min(offset + OFFSET_DRIFT_S, least)

    def _measured(self, sample: WheelSample) -> WheelSample:
        """``sample`` stamped when it was on the bus, on the receive times' (monotonic) clock: its
        bus stamp plus the clocks' offset (:meth:`_align`; never later than its receive time)."""
        if not sample.bus_stamp or self._offset is None:
            return sample
        return sample._replace(stamp=min(sample.bus_stamp + self._offset, sample.stamp))

    def _remember(self, samples: Mapping[str, WheelSample]) -> None:
        """Each trusted sample into its wheel's history (RAW_SAMPLES newest, one reference), stamped
        when it was on the bus; a wheel to be forgotten loses its history. A sample is new when it
        was received after the newest kept (its receive time, never its measured stamp: the clocks'
        offset rises a little every step, so the same PDO read at two steps would measure apart and
        be kept twice, its copies pushing out the samples an instant lies between)."""
        self._align(samples)
        for name, given in samples.items():
            if not math.isfinite(given.angle_rad) or (given.forget and not given.trusted):
                self._raw.pop(name, None)
                self._received.pop(name, None)
                continue
            if not given.trusted:
                continue
            sample = self._measured(given)
            raw = self._raw.get(name)
            if raw is None or raw[0].reference != sample.reference:
                self._raw[name] = (sample,)
            elif given.stamp > self._received[name] and sample.stamp > raw[0].stamp:
                self._raw[name] = (sample, *raw[:RAW_SAMPLES - 1])
            else:
                continue
            self._received[name] = given.stamp

    def _common_instant(self, samples: Mapping[str, WheelSample]) -> float:
        """The instant this step integrates to: the oldest newest sample among the wheels that
        may count, 0.0 if there is none."""
        return min((self._raw[n][0].stamp for n, s in samples.items() if s.trusted and n in self._raw), default=0.0)

    @staticmethod
    def _interpolate(points: Sequence[WheelSample], instant: float) -> float | None:
        """The angle at ``instant`` on the line through the two of ``points`` (in time order) around
        it; None when it is outside them (never extrapolated)."""
        for a, b in itertools.pairwise(points):
            if a.stamp <= instant <= b.stamp:
                share = (instant - a.stamp) / (b.stamp - a.stamp) if b.stamp > a.stamp else 1.0
                return a.angle_rad + share * (b.angle_rad - a.angle_rad)
        return points[0].angle_rad if len(points) == 1 and points[0].stamp == instant else None

    def _delta(self, name: str, sample: WheelSample | None, instant: float) -> tuple[float | None, _Update]:
        """(radians turned from this wheel's last point to ``instant``, 0.0 for nothing new, None
        where it counts for nothing; what becomes of its last point: kept, replaced, or forgotten).
        A wheel starting a reference starts at ``instant`` once its samples reach back to it (its
        side's others start there too), and waits for that meanwhile."""
        last = self._last.get(name)
        if sample is None or not sample.trusted or not math.isfinite(sample.angle_rad):
            forget = sample is None or sample.forget or not math.isfinite(sample.angle_rad)
            return None, _Update(name, None, forget)
        history = self._raw[name][::-1]  # in time order
        if last is None or last.reference != sample.reference:
            start = self._interpolate(history, instant)
            if start is None:  # its first sample is newer than the others': it starts at a later step
                return None, _Update(name, None, last is not None)
            return None, _Update(name, WheelSample(start, instant, sample.reference), False, restart=True)
        if instant <= last.stamp:
            return 0.0, _Update(name, None, False)  # nothing new: no motion, still trusted
        points = [last] + [p for p in history if p.stamp > last.stamp]
        angle = self._interpolate(points, instant)
        if angle is None:  # the instant lies before its last point: nothing new of it
            return 0.0, _Update(name, None, False)
        turned = angle - last.angle_rad - self._attributed.get(name, 0.0) / self.wheel_radius_m
        return turned, _Update(name, WheelSample(angle, instant, sample.reference), False)

    def _side(self, names: tuple[str, ...], samples: Mapping[str, WheelSample], instant: float) -> _Side:
        """One side: its mean distance (m), mean rim speed (m/s), the wheels that count, and the
        updates of their last samples. A wheel with no new sample counts as no motion: a side's
        mean over a fixed set of wheels adds up to the mean of their whole travel, whichever step
        each delta lands in. The speed is the trusted wheels' own velocity actual values (a PDO
        that carries no position makes no delta of its own time)."""
        distance = 0.0
        counted = 0
        speeds = []
        updates = []
        late = []
        for name in names:
            sample = samples.get(name)
            turned, update = self._delta(name, sample, instant)
            updates.append(update)
            if sample is not None and sample.trusted and math.isfinite(sample.velocity_rad_s):
                speeds.append(sample.velocity_rad_s * self.wheel_radius_m)
            if turned is None:
                if update.sample is None and not update.forget and name in self._last:
                    late.append(name)
                continue
            counted += 1
            distance += turned * self.wheel_radius_m
        if not counted:
            return _Side(0.0, 0.0, 0, updates, late)
        return _Side(distance / counted, sum(speeds) / len(speeds) if speeds else 0.0, counted, updates, late)

    def _commit(self, updates: list[_Update], *, deltas: bool) -> None:
        """Apply the updates: forgotten and restarted wheels always; a sample that carried a delta
        only with ``deltas`` (else its delta stays to be counted at the next trusted step)."""
        for update in updates:
            if update.forget:
                self._last.pop(update.name, None)
                self._never_settled_m += abs(self._attributed.pop(update.name, 0.0)) / self._side_size(update.name)
            elif update.sample is not None and (deltas or update.restart):
                self._last[update.name] = update.sample
                estimated = self._attributed.pop(update.name, 0.0)
                if update.restart:  # a new reference: no delta of its own will settle that estimate
                    self._never_settled_m += abs(estimated) / self._side_size(update.name)

    def _drop_late(self, names: tuple[str, ...]) -> None:
        """The late wheels of ``names`` forgotten, their history with them (a sample from before
        the gap never starts a new reference across it); what was estimated for them is never
        settled."""
        for name in names:
            if name in self._last:
                self._last.pop(name)
                self._raw.pop(name, None)
                self._received.pop(name, None)
                self._never_settled_m += abs(self._attributed.pop(name, 0.0)) / self._side_size(name)

    def _attribute(self, side: _Side) -> None:
        """A side's late wheels are taken to have travelled as its measuring wheels did (their mean):
        counted so now, and taken off their own delta when they are heard again."""
        for name in side.late:
            self._attributed[name] = self._attributed.get(name, 0.0) + side.distance_m

    def _side_size(self, name: str) -> int:
        return len(self.left) if name in self.left else len(self.right)

    @property
    def estimated_m(self) -> float:
        """Travel (m) estimated rather than measured so far: late wheels' shares not yet settled by
        their own samples, those never settled, and a side's travel dropped while the other side
        had no trusted wheel (at least that much is missing from the pose)."""
        return self._never_settled_m + sum(abs(m) / self._side_size(n) for n, m in self._attributed.items())

    def _without_a_side(self, samples: Mapping[str, WheelSample], instant: float, left: _Side, right: _Side) -> OdometryStep:
        """A step where one side, or both, has no trusted wheel (:meth:`step`): each such side judged
        alike, the left as the right. The pose waits, still trusted, only where every silent side is
        only late; the other side's travel is kept only where every silent side has a late wheel whose
        next sample will carry the gap."""
        quiet = [(label, names, side) for label, names, side in (("left", self.left, left), ("right", self.right, right))
                 if not side.counted]
        updates = left.updates + right.updates
        self._commit([u for u in updates if u.forget or u.restart], deltas=False)
        only_silent = all(any(w is not None and w.silent for w in waiting)
                          and all(w is not None and (w.silent or w.forget) for w in waiting)
                          for waiting in ([samples.get(n) for n in names] for _, names, _ in quiet))
        late = all(bool(side.late) for _, _, side in quiet)
        silent = tuple(n for _, names, _ in quiet for n in names)
        if late and not only_silent and self._instant and instant - self._instant > MAX_BRIDGED_GAP_S:
            self._drop_late(silent)  # too long a gap for one step: they start anew, as lost wheels do
            late = False
        if not late:  # nothing will carry the gap on a silent side: drop the other's too
            self._commit(updates, deltas=True)
            self._attribute(left)
            self._attribute(right)
            # travel the pose will never have: estimated from now on (the silent side's own is unknown)
            self._never_settled_m += abs(left.distance_m) + abs(right.distance_m)
        if only_silent:
            # a PDO or two late (within the staleness bound): the pose waits for them, still trusted
            return OdometryStep(self.pose, self._twist, True, estimated_m=self.estimated_m)
        sides = " and ".join(label for label, _, _ in quiet) + (" sides" if len(quiet) > 1 else " side")
        reasons = ", ".join(f"{n} {self._why(samples.get(n))}" for n in silent)
        return OdometryStep(self.pose, Twist2D(), False, f"odometry stopped: no trusted wheel on the {sides} ({reasons})",
                            self.estimated_m)

    def step(self, samples: Mapping[str, WheelSample]) -> OdometryStep:
        """Integrate what the wheels measured since the last step.

        A step with a side that has no trusted wheel integrates nothing. Whether the other side's
        travel meanwhile is kept for later or dropped depends on the silent side: if one of its
        wheels is only late (its last sample kept), its next sample will carry the gap, so the
        other side's travel is kept to be paired with it; if all of them were lost or start anew,
        nothing of theirs will cover the gap, and the other side's travel over it is dropped too
        (the heading stays the wheels': both sides lose the same interval)."""
        self._remember(samples)
        instant = self._common_instant(samples)
        left, right = self._side(self.left, samples, instant), self._side(self.right, samples, instant)
        if not left.counted or not right.counted:
            return self._without_a_side(samples, instant, left, right)
        if instant <= self._instant:  # nothing measured on both sides since the last step's instant
            self._commit([u for u in left.updates + right.updates if u.forget or u.restart], deltas=False)
            return OdometryStep(self.pose, self._twist, True, estimated_m=self.estimated_m)
        self._instant = instant
        self._commit(left.updates + right.updates, deltas=True)
        self._attribute(left)
        self._attribute(right)
        forward = (left.distance_m + right.distance_m) / 2.0
        turn = (right.distance_m - left.distance_m) / self.track_width_m
        self.pose = integrate(self.pose, Twist2D(forward, turn), 1.0)  # distances: one unit of "time"
        twist = self._twist = Twist2D((left.speed_m_s + right.speed_m_s) / 2.0,
                                      (right.speed_m_s - left.speed_m_s) / self.track_width_m)
        return OdometryStep(self.pose, twist, True, estimated_m=self.estimated_m, measured_at=instant)

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
