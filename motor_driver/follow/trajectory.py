"""Set-point trajectories for a streamed drive (cyclic synchronous or interpolated position: one
set-point per SYNC period, the driver's ``stream_position``): pure generators, no I/O and no
clock. The caller sends each value and waits one period; the drive's own limits are checked
where the value is sent, not here.

:func:`trapezoid` is the point-to-point move of a drive without profile position mode (the
SCHUNK PRL120): accelerate at the profile acceleration, cruise at the speed, decelerate, so that
the set-points never ask for more than either; a move too short to reach the speed is a triangle.

:class:`Spline` is a joint trajectory's interpolation (FollowJointTrajectory, :mod:`motor_driver.follow`):
between two points a quintic, a cubic or a line, as ros2_control's joint_trajectory_controller does,
sampled at each SYNC by the group that follows it.
"""

from __future__ import annotations

import bisect
import itertools
import math
from collections.abc import Iterator

from can_config.errors import CommandRejected


def _positive(name: str, value: float) -> None:
    if not (math.isfinite(value) and value > 0):
        raise CommandRejected(f"{name} {value!r}: allowed a finite value > 0")


def trapezoid(start_deg: float, target_deg: float, speed_deg_s: float, accel_deg_s2: float,
              period_s: float) -> Iterator[float]:
    """The positions from ``start_deg`` (excluded) to ``target_deg`` (the last value, exactly),
    one every ``period_s``: a trapezoid of velocity, peaking at ``speed_deg_s`` (or below it on a
    short move) and ramped at ``accel_deg_s2``. A move of no distance is its target once.
    :class:`CommandRejected` for a non-finite position or a speed, acceleration or period <= 0."""
    for name, value in (("start_deg", start_deg), ("target_deg", target_deg)):
        if not math.isfinite(value):
            raise CommandRejected(f"{name} {value!r}: allowed a finite angle")
    for name, value in (("speed_deg_s", speed_deg_s), ("accel_deg_s2", accel_deg_s2), ("period_s", period_s)):
        _positive(name, value)
    return _trapezoid(start_deg, target_deg, speed_deg_s, accel_deg_s2, period_s)


def _trapezoid(start_deg: float, target_deg: float, speed: float, accel: float, period: float) -> Iterator[float]:
    distance = target_deg - start_deg
    direction = 1.0 if distance >= 0 else -1.0
    span = abs(distance)
    ramp = min(speed * speed / (2 * accel), span / 2)  # the distance of each ramp (v^2 / 2a, or half the way)
    peak = math.sqrt(2 * accel * ramp)  # the speed reached
    t_ramp = peak / accel
    t_total = 2 * t_ramp + ((span - 2 * ramp) / peak if peak else 0.0)
    ticks = max(1, math.ceil(t_total / period - 1e-9))  # the last tick lands on (or just after) the end
    for tick in range(1, ticks):
        t = tick * period
        if t < t_ramp:
            done = 0.5 * accel * t * t
        elif t > t_total - t_ramp:
            done = span - 0.5 * accel * (t_total - t) ** 2
        else:
            done = ramp + peak * (t - t_ramp)
        yield start_deg + direction * done
    yield target_deg


# ---------------------------------------------------------------------- a joint trajectory's spline
#: A knot of one joint: position (deg), velocity (deg/s) or None, acceleration (deg/s^2) or None.
Knot = tuple[float, float | None, float | None]


def segment(p0: float, v0: float | None, a0: float | None, p1: float, v1: float | None, a1: float | None,
            duration_s: float) -> tuple[float, ...]:
    """The polynomial (coefficients c0, c1, ... of t^0, t^1, ...) from one knot to the next over
    ``duration_s``, as ros2_control's joint_trajectory_controller interpolates: quintic where both
    knots give velocity and acceleration, cubic where both give velocity, else linear (positions only).
    The polynomial meets each knot's position, and its velocity and acceleration where it uses them."""
    t = duration_s
    if v0 is not None and v1 is not None and a0 is not None and a1 is not None:
        t2, t3 = t * t, t * t * t
        return (p0, v0, a0 / 2,
                (-20 * p0 + 20 * p1 - 3 * a0 * t2 + a1 * t2 - 12 * v0 * t - 8 * v1 * t) / (2 * t3),
                (30 * p0 - 30 * p1 + 3 * a0 * t2 - 2 * a1 * t2 + 16 * v0 * t + 14 * v1 * t) / (2 * t3 * t),
                (-12 * p0 + 12 * p1 - a0 * t2 + a1 * t2 - 6 * v0 * t - 6 * v1 * t) / (2 * t3 * t2))
    if v0 is not None and v1 is not None:
        return (p0, v0, (-3 * p0 + 3 * p1 - 2 * v0 * t - v1 * t) / (t * t),
                (2 * p0 - 2 * p1 + v0 * t + v1 * t) / (t * t * t))
    return (p0, (p1 - p0) / t)


def evaluate(coefficients: tuple[float, ...], t: float) -> tuple[float, float, float]:
    """Position, velocity and acceleration of a polynomial at ``t`` (Horner)."""
    p = v = a = 0.0
    n = len(coefficients)
    for i in range(n - 1, -1, -1):
        c = coefficients[i]
        p = p * t + c
        if i >= 1:
            v = v * t + i * c
        if i >= 2:
            a = a * t + i * (i - 1) * c
    return p, v, a


class Spline:
    """One trajectory of several joints: knots at ``times_s`` (the first at 0, strictly increasing),
    ``knots[k][j]`` the knot of joint ``j`` at ``times_s[k]``. :meth:`sample` gives each joint's
    position, velocity and acceleration at a time: the start before 0, the last knot's position at
    rest after the end. Built once, never changed; pure (no clock, no I/O)."""

    def __init__(self, times_s: tuple[float, ...], knots: tuple[tuple[Knot, ...], ...]) -> None:
        if len(times_s) < 2 or times_s[0] != 0.0 or any(b <= a for a, b in itertools.pairwise(times_s)):
            raise CommandRejected(f"knot times {times_s!r}: allowed two or more, the first 0, strictly increasing")
        self.times_s = times_s
        self.end_s = times_s[-1]
        self._last = tuple(k[0] for k in knots[-1])
        self._polys = [tuple(segment(*a, *b, t1 - t0) for a, b in zip(knots[i], knots[i + 1], strict=True))
                       for i, (t0, t1) in enumerate(itertools.pairwise(times_s))]
        self._first = tuple(evaluate(p, 0.0) for p in self._polys[0])

    def segments(self) -> Iterator[tuple[float, float, tuple[tuple[float, ...], ...]]]:
        """Each segment's start time, duration and every joint's polynomial on it (local time)."""
        for t0, t1, polys in zip(self.times_s, self.times_s[1:], self._polys, strict=False):
            yield t0, t1 - t0, polys

    def sample(self, t: float) -> tuple[tuple[float, float, float], ...]:
        """(position, velocity, acceleration) of every joint at ``t`` s from the start."""
        if t <= 0.0:
            return self._first
        if t >= self.end_s:
            return tuple((p, 0.0, 0.0) for p in self._last)
        i = bisect.bisect_right(self.times_s, t) - 1
        local = t - self.times_s[i]
        return tuple(evaluate(p, local) for p in self._polys[i])


#: The finest share of a segment :func:`excursion` halves down to: there a hull that leaves a bound
#: while the values at its ends do not lies within rounding of the curve (2**-30 of a 10 s segment: 9 ns).
EXCURSION_DEPTH = 30
#: C(k, i) / C(n, i), the change from the power basis to Bernstein's, for the degrees a segment has (0-5).
_TO_BERNSTEIN = tuple(tuple(tuple(math.comb(k, i) / math.comb(n, i) for i in range(k + 1)) for k in range(n + 1))
                      for n in range(6))


def derivative(coefficients: tuple[float, ...]) -> tuple[float, ...]:
    """The derivative of a polynomial (coefficients of t^0, t^1, ...): of a constant, 0."""
    return tuple(i * c for i, c in enumerate(coefficients))[1:] or (0.0,)


def _bernstein(coefficients: tuple[float, ...], duration_s: float) -> list[float]:
    """The polynomial on [0, duration_s] in the Bernstein basis of its degree: its values lie within
    the hull of these (their min and max), and the first and last are its values at the ends."""
    n = len(coefficients) - 1
    scaled = [c * duration_s**i for i, c in enumerate(coefficients)]
    return [sum(r * a for r, a in zip(ratios, scaled, strict=False)) for ratios in _TO_BERNSTEIN[n]]


def _halves(b: list[float]) -> tuple[list[float], list[float]]:
    """de Casteljau at the middle: the Bernstein coefficients of each half."""
    left, right, row = [b[0]], [b[-1]], b
    while len(row) > 1:
        row = [(x + y) / 2 for x, y in itertools.pairwise(row)]
        left.append(row[0])
        right.append(row[-1])
    return left, right[::-1]


def excursion(coefficients: tuple[float, ...], duration_s: float, low: float, high: float) -> tuple[float, float] | None:
    """The first (time, value) found where a polynomial leaves [low, high] over [0, duration_s], or None
    where it stays within: decided for every instant, not at samples, whatever the duration (the hull of
    its Bernstein coefficients bounds its values; where a hull crosses a bound its interval is halved,
    earlier half first, until a value beyond the bound is found or every hull lies within)."""
    stack = [(0.0, 1.0, _bernstein(coefficients, duration_s))]
    while stack:
        u0, u1, b = stack.pop()
        if low <= min(b) and max(b) <= high:
            continue
        for u, value in ((u0, b[0]), (u1, b[-1])):
            if not low <= value <= high:
                return u * duration_s, value
        if u1 - u0 > 2.0**-EXCURSION_DEPTH:
            left, right = _halves(b)
            middle = (u0 + u1) / 2
            stack += [(middle, u1, right), (u0, middle, left)]
    return None


def sample_times(end_s: float, period_s: float) -> Iterator[float]:
    """The times of a trajectory's set-points, one a period from ``period_s`` on, the last at
    ``end_s`` exactly (the tick that lands on or just after the end)."""
    _positive("period_s", period_s)
    ticks = max(1, math.ceil(end_s / period_s - 1e-9))
    for tick in range(1, ticks):
        yield tick * period_s
    yield end_s
