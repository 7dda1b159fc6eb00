"""What the drive system says of a wheel, and which wheels it has left out (pure: no rclpy).

Every judgement here is the wheel's verdict (:mod:`motor_driver.drive.verdict`, carried by its
snapshot): :func:`wheel_problem` says it (the cause and what helps); :func:`odometry_sample`
turns a wheel's snapshot into what the odometry may count (:mod:`motor_driver.rover.odometry`): only a
usable wheel heard within its PDO period; :class:`WheelsOut` is ``on_wheel_loss: continue``'s
book of the wheels left out, and when each may come back.

Owner: the drive system's control loop (one thread, the executor that runs its tick).
"""

from __future__ import annotations

import math
from collections.abc import Collection, Iterable, Mapping, Sequence
from dataclasses import dataclass

from motor_driver.drive import DriveState
from motor_driver.drive.verdict import Condition, Verdict, judge, ms
from motor_driver.rover.odometry import WheelSample


def wheel_problem(state: DriveState) -> str:
    """Why the wheel of ``state`` cannot be driven, and what helps; "" when it can."""
    verdict = state.verdict
    return "" if verdict.usable else verdict.text()


def out_verdict(state: DriveState, reason: str) -> Verdict:
    """The verdict on a wheel the drive system left out for ``reason``."""
    return judge(state.facts._replace(left_out=reason))


def problems(states: Iterable[DriveState]) -> str:
    """The first wheel's problem, and how many more have one (with their names)."""
    said = [(s.name, wheel_problem(s)) for s in states]
    said = [(name, text) for name, text in said if text]
    if not said:
        return ""
    more = f" (and {len(said) - 1} more: {', '.join(n for n, _ in said[1:])})" if len(said) > 1 else ""
    return said[0][1] + more


#: a wheel not heard for longer than this many of its PDO periods (SYNC periods) is counted by
#: the odometry as late, not as standing still (its next sample settles the gap)
PDO_SILENCE_PERIODS = 1.5
#: nor is a wheel whose newest sample is older than its side's newest by more than this many
#: periods: a sample of an earlier SYNC than its side's others is late too
SIDE_LAG_PERIODS = 0.5


def odometry_sample(state: DriveState, pdo_period_s: float, *, driven: bool = True,
                    side_newest_s: float = 0.0) -> WheelSample:
    """What the odometry may take from a wheel: its position at its own TPDO's receive time
    (monotonic) and bus stamp, and its reference. Counted only when usable and heard within PDO_SILENCE_PERIODS of its PDO period
    and in its side's newest SYNC (``side_newest_s``, the newest receive time of its side);
    else, if usable or only late, it keeps its last sample (its next one settles the gap);
    anything else (lost, out, disabled, quick-stopped, faulted, re-booting) forgets it.
    ``driven``: some wheel of the rover is usable; when none is (the rover disarmed, standing or
    pushed), every wheel whose data is news counts: what they measure is all the motion there is."""
    verdict = state.verdict
    received = state.position_rx  # the position's own TPDO: a later one without a position is no news of it
    # the verdict's age counts from when the data was last whole: the position's own is older by
    # the time between (a hand-made state without it: from its newest TPDO)
    age_s = verdict.age_s + ((state.whole_rx or state.rx_monotonic) - received) if received else math.inf
    silent = age_s > PDO_SILENCE_PERIODS * pdo_period_s or side_newest_s - received > SIDE_LAG_PERIODS * pdo_period_s
    if verdict.usable or (not driven and verdict.fresh):
        trusted, forget, why = not silent, False, f"its position silent for {ms(age_s)}" if silent else ""
    else:
        trusted, forget, why = False, verdict.condition is not Condition.LATE, verdict.cause
    return WheelSample(math.radians(state.angle_deg), received, state.reference, trusted and bool(received),
                       why or ("" if received else "no position yet"),
                       forget=forget, silent=not forget and not trusted and verdict.condition is not Condition.LATE,
                       velocity_rad_s=math.radians(state.velocity_deg_s), bus_stamp=state.position_stamp)


def odometry_samples(states: Mapping[str, DriveState], sides: Iterable[Sequence[str]],
                     pdo_period_s: Mapping[str, float]) -> dict[str, WheelSample]:
    """Every wheel's :func:`odometry_sample`, each side's newest receive time and whether any
    wheel is driven judged once."""
    driven = any(s.verdict.usable for s in states.values())
    samples = {}
    for side in sides:
        newest = max((states[n].position_rx for n in side if states[n].verdict.fresh), default=0.0)
        for name in side:
            samples[name] = odometry_sample(states[name], pdo_period_s[name], driven=driven, side_newest_s=newest)
    return samples


@dataclass
class OutWheel:
    reason: str
    enables: int  # the driver's count of its completed enables when it went out


class WheelsOut:
    """``on_wheel_loss: continue``: the wheels left out, each with its reason. A wheel goes out
    when its verdict is not usable while the rover drives (lost, late, faulted, another master's,
    stopped): it is told to stop; it comes back only once its verdict is usable again after an
    enable the driver completed since it went out (/arm, its own enable, or, with
    restore_enable_after_reboot, the driver's enable after a reset it configured again unless a
    stop came first): never by itself, still running
    from before. The enable is read from the driver's count of them, not from states seen between
    two ticks: an /arm that stops and enables a wheel within one tick takes it back all the same."""

    def __init__(self, left: Sequence[str], right: Sequence[str]) -> None:
        self.left, self.right = tuple(left), tuple(right)
        self.out: dict[str, OutWheel] = {}

    def update(self, states: dict[str, DriveState], driving: bool) -> tuple[list[str], list[str]]:
        """(wheels that went out now, wheels that came back now)."""
        went, back = [], []
        for name, state in states.items():
            verdict = state.verdict
            out = self.out.get(name)
            if out is None:  # held (the lifecycle node inactive) is the whole rover's state, not a wheel's loss
                if driving and not verdict.usable and verdict.condition is not Condition.HELD:
                    self.out[name] = OutWheel(verdict.text(), state.facts.enables)
                    went.append(name)
                continue
            if verdict.usable and state.facts.enables > out.enables:
                del self.out[name]
                back.append(name)
        return went, back

    def still_running(self, states: dict[str, DriveState], enabling: Collection[str] = ()) -> list[str]:
        """Wheels out that still run under their own steam (usable, armed from before they went
        out: no stop of ours reached the channel since, nor an enable): told to stop again. Not a
        wheel in ``enabling`` (an enable under way, /arm taking it back: Operation Enabled is usable
        before the enable is counted, and a stop then interrupted the /arm; a loaded CI showed it);
        one whose enable fails is told at the next look."""
        return [n for n in self.out if states[n].verdict.usable and n not in enabling]

    def share(self) -> float:
        """The share of wheels left on the weaker side (1.0: all; 0.0: a side has none)."""
        return min(self._left(self.left), self._left(self.right))

    def _left(self, side: tuple[str, ...]) -> float:
        return sum(1 for n in side if n not in self.out) / len(side)

    def empty_side(self) -> str:
        """The side with no wheel left ("left", "right"), or ""."""
        return "left" if not self._left(self.left) else "right" if not self._left(self.right) else ""

    def summary(self) -> str:
        return "; ".join(f"{n} out ({o.reason})" for n, o in self.out.items())
