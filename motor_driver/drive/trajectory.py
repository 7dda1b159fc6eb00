"""Set-point trajectories for a streamed drive (cyclic synchronous or interpolated position: one
set-point per SYNC period, the driver's ``stream_position``): pure generators, no I/O and no
clock. The caller sends each value and waits one period; the drive's own limits are checked
where the value is sent, not here.

:func:`trapezoid` is the point-to-point move of a drive without profile position mode (the
SCHUNK PRL120): accelerate at the profile acceleration, cruise at the speed, decelerate, so that
the set-points never ask for more than either; a move too short to reach the speed is a triangle.
"""

from __future__ import annotations

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
