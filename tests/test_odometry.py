"""Tier 1: odometry from the wheels' measured positions (pure; motor_driver/rover/odometry.py).

The properties the rover's /odom stands on: the heading is the wheels' own (whichever step
each wheel's sample lands in), a new position reference is never a jump, a lost wheel adds
nothing, a side with no trusted wheel stops the integration and says why."""

from __future__ import annotations

import math

from hypothesis import example, given, settings
from hypothesis import strategies as st

from motor_driver.rover.odometry import MAX_BRIDGED_GAP_S, WheelOdometry, WheelSample, yaw_from_wheels

LEFT, RIGHT = ("fl", "ml", "rl"), ("fr", "mr", "rr")
TRACK_M, RADIUS_M = 0.6, 0.1
ACCEL_RAD_S2 = 10.0  # a wheel's acceleration (1 m/s2 at the rim)


def odometry() -> WheelOdometry:
    return WheelOdometry(LEFT, RIGHT, TRACK_M, RADIUS_M)


def samples(angles: dict[str, float], t: float, reference: int = 1, velocity: float = 0.0,
            **trust: bool) -> dict[str, WheelSample]:
    return {n: WheelSample(a, t, reference, trust.get(n, True), "" if trust.get(n, True) else "lost", forget=True,
                           velocity_rad_s=velocity) for n, a in angles.items()}


def test_straight_driving_moves_forward_by_the_rim_travel() -> None:
    odo = odometry()
    for k in range(101):
        step = odo.step(samples({n: 0.1 * k for n in LEFT + RIGHT}, 0.01 * k, velocity=10.0))
    assert step.trusted
    assert math.isclose(step.pose.x_m, 10.0 * RADIUS_M, rel_tol=1e-9)  # 10 rad at 0.1 m
    assert abs(step.pose.yaw_rad) < 1e-12
    assert math.isclose(step.twist.linear_m_s, 1.0, rel_tol=1e-9)  # 10 rad/s at 0.1 m


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.lists(st.floats(-0.5, 0.5), min_size=6, max_size=6),
                          st.lists(st.booleans(), min_size=6, max_size=6)), min_size=2, max_size=60))
def test_the_heading_is_the_wheels_whichever_step_their_samples_land_in(
        moves: list[tuple[list[float], list[bool]]]) -> None:
    """Each wheel moves by its own increments and is sampled at its own times (a sample may be
    late: the wheel sends nothing new in a step); at the end, after every wheel sent its newest
    position, the yaw is exactly what the wheel positions say."""
    odo = odometry()
    names = LEFT + RIGHT
    angle = dict.fromkeys(names, 0.0)
    sent = {n: WheelSample(0.0, 0.0, 1) for n in names}
    odo.step(sent)
    for k, (deltas, fresh) in enumerate(moves, start=1):
        for n, d, f in zip(names, deltas, fresh, strict=True):
            angle[n] += d
            if f:
                sent[n] = WheelSample(angle[n], float(k), 1)
        odo.step(dict(sent))
    final = {n: WheelSample(angle[n], float(len(moves) + 1), 1) for n in names}
    step = odo.step(final)
    want = yaw_from_wheels([angle[n] for n in LEFT], [angle[n] for n in RIGHT], TRACK_M, RADIUS_M)
    assert math.isclose(math.remainder(step.pose.yaw_rad - want, math.tau), 0.0, abs_tol=1e-9)


@settings(max_examples=100, deadline=None)
@given(st.floats(-1e6, 1e6), st.sampled_from(LEFT + RIGHT), st.integers(1, 20))
def test_a_new_position_reference_is_never_a_jump(jump_rad: float, wheel: str, at: int) -> None:
    """A reboot or a homing gives a wheel a new zero: its first sample in the new reference
    starts anew (here the rover stands still, so nothing may move, whatever the jump)."""
    odo = odometry()
    for k in range(30):
        reference = 2 if k >= at else 1
        angles = {n: (jump_rad if n == wheel and k >= at else 0.0) for n in LEFT + RIGHT}
        step = odo.step({n: WheelSample(a, float(k), reference if n == wheel else 1) for n, a in angles.items()})
        assert step.trusted or k == 0
        assert step.pose.x_m == 0.0 and step.pose.y_m == 0.0 and step.pose.yaw_rad == 0.0


def test_a_side_with_no_trusted_wheel_stops_the_integration_and_says_why() -> None:
    odo = odometry()
    odo.step(samples(dict.fromkeys(LEFT + RIGHT, 0.0), 0.0))
    moved = odo.step(samples(dict.fromkeys(LEFT + RIGHT, 1.0), 0.1))
    assert moved.trusted and moved.pose.x_m > 0
    lost = odo.step(samples(dict.fromkeys(LEFT + RIGHT, 5.0), 0.2, fl=False, ml=False, rl=False))
    assert not lost.trusted and lost.pose == moved.pose and lost.twist.linear_m_s == 0.0
    assert "left side" in lost.why_not and "fl lost" in lost.why_not
    # back: the left wheels start anew (no jump, and the right side's travel meanwhile cannot be
    # paired with anything on the left: not integrated), then both sides count again
    restart = odo.step(samples(dict.fromkeys(LEFT + RIGHT, 9.0), 0.3))
    assert not restart.trusted and restart.pose == moved.pose and "new position reference" in restart.why_not
    again = odo.step(samples(dict.fromkeys(LEFT + RIGHT, 10.0), 0.4))
    assert again.trusted and abs(again.pose.yaw_rad) < 1e-12
    assert math.isclose(again.pose.x_m, 2 * RADIUS_M, rel_tol=1e-9)
    # the right side's 8 rad over the two steps is missing from the pose: the pose's variance says it
    assert moved.estimated_m == 0.0
    assert math.isclose(again.estimated_m, 8.0 * RADIUS_M, rel_tol=1e-9)


def wheel(state: str, angle: float, t: float) -> WheelSample:
    """A wheel's sample: fresh, only late (silent within its staleness bound) or lost."""
    if state == "fresh":
        return WheelSample(angle, t, 1)
    if state == "late":
        return WheelSample(angle, t, 1, False, "stale for 20 ms", silent=True)
    return WheelSample(angle, t, 1, False, "lost", forget=True)


def test_a_late_side_beside_a_lost_side_is_judged_alike_either_way_round() -> None:
    """One side only late, the other lost: not trusted, naming the lost wheels, whichever side they are
    on (the right side's loss was not looked at where the left had no counted wheel: /odom went silent
    instead of saying so)."""
    for late_side, lost_side in ((LEFT, RIGHT), (RIGHT, LEFT)):
        odo = odometry()
        odo.step(samples(dict.fromkeys(LEFT + RIGHT, 0.0), 0.0))
        step = odo.step({**{n: wheel("late", 0.0, 0.0) for n in late_side},
                         **{n: wheel("lost", 0.0, 0.1) for n in lost_side}})
        assert not step.trusted, lost_side
        assert all(f"{n} lost" in step.why_not for n in lost_side), step.why_not


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.lists(st.sampled_from(("fresh", "late", "lost")), min_size=6, max_size=6),
                          st.lists(st.floats(-0.5, 0.5), min_size=6, max_size=6)), min_size=1, max_size=12))
def test_the_rover_mirrored_is_judged_mirrored(steps: list[tuple[list[str], list[float]]]) -> None:
    """Any run of fresh, late and lost wheels, and the same run with left and right swapped: the
    same trust each step, the same travel, the opposite turn."""
    names, mirrored = LEFT + RIGHT, RIGHT + LEFT
    odo, twin = odometry(), odometry()
    angles = dict.fromkeys(names, 0.0)
    odo.step(samples(dict.fromkeys(names, 0.0), 0.0))
    twin.step(samples(dict.fromkeys(names, 0.0), 0.0))
    last = {n: WheelSample(0.0, 0.0, 1) for n in names}
    for k, (states, deltas) in enumerate(steps, start=1):
        for n, state, d in zip(names, states, deltas, strict=True):
            angles[n] += d
            last[n] = wheel(state, angles[n], 0.01 * k) if state != "late" else wheel("late", last[n].angle_rad,
                                                                                     last[n].stamp)
        one = odo.step(dict(last))
        other = twin.step({m: last[n] for n, m in zip(names, mirrored, strict=True)})
        assert one.trusted == other.trusted, (k, one.why_not, other.why_not)
        assert math.isclose(one.pose.x_m, other.pose.x_m, abs_tol=1e-9)
        assert math.isclose(one.pose.yaw_rad, -other.pose.yaw_rad, abs_tol=1e-9)


def test_one_wheel_lost_the_side_carries_on_with_the_others() -> None:
    odo = odometry()
    odo.step(samples(dict.fromkeys(LEFT + RIGHT, 0.0), 0.0))
    angles = dict.fromkeys(LEFT + RIGHT, 1.0)
    angles["fl"] = 50.0  # lost, and whatever it says is not believed
    step = odo.step(samples(angles, 0.1, fl=False))
    assert step.trusted and abs(step.pose.yaw_rad) < 1e-12
    assert math.isclose(step.pose.x_m, RADIUS_M, rel_tol=1e-9)


def test_a_late_wheel_keeps_its_last_sample_and_counts_the_gap_after() -> None:
    """Data that is only late (stale, the reference unchanged) adds nothing meanwhile; the next
    sample carries what the encoder counted over the gap: no distance is lost."""
    odo = odometry()
    odo.step(samples(dict.fromkeys(LEFT + RIGHT, 0.0), 0.0))
    stale = {n: WheelSample(0.0, 0.0, 1, False, "stale") for n in LEFT + RIGHT}
    assert not odo.step(stale).trusted
    step = odo.step(samples(dict.fromkeys(LEFT + RIGHT, 2.0), 0.5))
    assert step.trusted and math.isclose(step.pose.x_m, 2.0 * RADIUS_M, rel_tol=1e-9)


def test_a_late_wheel_back_in_a_new_reference_leaves_its_estimate_estimated() -> None:
    """fl late for three steps (its share taken as its side's others'), then heard again in a new
    position reference (its counter wrapped, it was homed): nothing of its own will settle the
    estimate, which stays in ``estimated_m`` (it fell to 0, and the covariance with it)."""
    odo = odometry()
    odo.step(samples(dict.fromkeys(LEFT + RIGHT, 0.0), 0.0))
    odo.step(samples(dict.fromkeys(LEFT + RIGHT, 1.0), 0.02))
    late = WheelSample(1.0, 0.02, 1, False, "silent", silent=True)
    for t in (0.04, 0.06, 0.08):
        now = samples(dict.fromkeys(LEFT + RIGHT, 1.0 + 50 * (t - 0.02)), t)
        step = odo.step({**now, "fl": late})
    estimated = step.estimated_m
    assert math.isclose(estimated, 3 * RADIUS_M / len(LEFT), rel_tol=1e-9)  # 3 rad of fl's, one wheel of three
    for t in (0.10, 0.12):
        now = samples(dict.fromkeys(LEFT + RIGHT, 1.0 + 50 * (t - 0.02)), t)
        step = odo.step({**now, "fl": WheelSample(-1.0e6 + 50 * t, t, 2)})
    assert step.trusted and math.isclose(step.estimated_m, estimated, rel_tol=1e-9)


def test_the_same_pdos_read_again_measure_nothing() -> None:
    """A step that reads the PDOs the last step read measures nothing (``measured_at`` 0.0: /odom
    says nothing as measured), even while the clocks' offset rises (every sample later than the
    least seen): the same data stamped anew would be published as a new measurement, and kept
    twice it pushed out the samples an instant lies between."""
    odo = odometry()

    def read(angle: float, bus_s: float, late_s: float) -> dict[str, WheelSample]:
        return {n: WheelSample(angle, 100.0 + bus_s + late_s, 1, bus_stamp=bus_s) for n in LEFT + RIGHT}

    odo.step(read(0.0, 1.0, 0.001))  # the clocks' offset: 1 ms of lateness
    first = odo.step(read(1.0, 1.1, 0.003))  # every answer later since: the offset rises a step's slew
    assert first.measured_at
    for _ in range(5):
        again = odo.step(read(1.0, 1.1, 0.003))
        assert again.trusted and not again.measured_at, again
        assert again.pose == first.pose
    step = odo.step(read(2.0, 1.2, 0.003))
    assert step.measured_at > first.measured_at and math.isclose(step.pose.x_m, 2.0 * RADIUS_M, rel_tol=1e-9)


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.floats(-0.5, 0.5), st.floats(-0.5, 0.5),
                          st.lists(st.booleans(), min_size=6, max_size=6)), min_size=2, max_size=60))
def test_late_data_never_turns_the_heading(moves: list[tuple[float, float, list[bool]]]) -> None:
    """A skid-steer side's wheels turn alike; any of them late (stale: untrusted, last sample kept)
    at random, a whole side at a time too. Once every wheel is fresh again the heading is exactly
    the wheels': a late wheel's gap is its side's others' while they measure, and a whole late
    side's gap is paired with the other side's travel meanwhile, never dropped on one side only (a
    loaded host made one side's PDOs late and /odom turned 4 deg driving straight). The whole run
    lasts less than MAX_BRIDGED_GAP_S (a longer gap starts the late side anew:
    tests/test_odometry_verdict.py)."""
    odo = odometry()
    names = LEFT + RIGHT
    angle = dict.fromkeys(names, 0.0)
    tick = MAX_BRIDGED_GAP_S / 62
    odo.step({n: WheelSample(0.0, 0.0, 1) for n in names})
    for k, (left, right, fresh) in enumerate(moves, start=1):
        step = {}
        for n, f in zip(names, fresh, strict=True):
            angle[n] += left if n in LEFT else right
            step[n] = WheelSample(angle[n], k * tick, 1) if f else WheelSample(0.0, 0.0, 1, False, "stale")
        odo.step(step)
    final = odo.step({n: WheelSample(angle[n], (len(moves) + 1) * tick, 1) for n in names})
    want = yaw_from_wheels([angle[n] for n in LEFT], [angle[n] for n in RIGHT], TRACK_M, RADIUS_M)
    assert final.trusted
    assert math.isclose(math.remainder(final.pose.yaw_rad - want, math.tau), 0.0, abs_tol=1e-9)


@settings(max_examples=40, deadline=None)
@given(skew_s=st.floats(0.0, 0.0099), jitter=st.lists(st.floats(0.0, 0.004), min_size=1, max_size=8),
       rate=st.floats(-10.0, 10.0).filter(lambda r: abs(r) > 0.01))
def test_buses_with_skewed_syncs_are_paired_by_when_they_measured(skew_s: float, jitter: list[float],
                                                                  rate: float) -> None:
    """Two buses, SYNC every 10 ms, can1's ``skew_s`` after can0's; the step reads each side's
    newest sample at 20 ms, whatever SYNC it came from, each received late by its own jitter (a
    receive thread's wake-up) but stamped on the bus when it was sent. Every wheel turns alike:
    once a wheel has been received with the least lateness (the alignment of bus stamps to the
    receive clock learns it), the heading stays 0 at every step (within the alignment's slew allowance, OFFSET_DRIFT_S a
    sample, and a straight line between two samples 10 ms apart at ACCEL_RAD_S2: 2e-4 rad; a sample
    of one SYNC paired with one of another is 0.017 rad at 10 rad/s),
    and the rover moves by each wheel's travel."""
    odo = odometry()
    period = 0.01
    mono_minus_wall = 5000.0  # the receive clock (monotonic) against the bus stamps' (wall)
    ramp_s = abs(rate) / ACCEL_RAD_S2

    def travelled_s(t: float) -> float:  # seconds at full speed: from standing, at ACCEL_RAD_S2
        return 0.0 if t <= 0.0 else 0.5 * t * t / ramp_s if t < ramp_s else t - 0.5 * ramp_s

    def newest(side: tuple[str, ...], now: float, offset: float, k: int) -> dict[str, WheelSample]:
        sync = math.floor((now - offset) / period) * period + offset  # the newest SYNC before now
        lateness = jitter[k % len(jitter)]
        angle = rate * travelled_s(sync - 1.5)  # standing until 1.5 s: the alignment learns each wheel's lateness
        return {n: WheelSample(angle, sync + mono_minus_wall + 0.0005 + lateness, 1, bus_stamp=sync) for n in side}

    for k in range(1, 100):
        now = 1.0 + k * 0.02 + 0.003
        step = odo.step(newest(LEFT, now, 0.0, k) | newest(RIGHT, now, skew_s, k + 3))
        assert abs(step.pose.yaw_rad) < 2e-4, (k, step.pose.yaw_rad)
    assert step.trusted and step.measured_at
    assert math.isclose(step.pose.x_m, rate * travelled_s(step.measured_at - mono_minus_wall - 0.0005 - 1.5) * RADIUS_M,
                        rel_tol=0.01, abs_tol=abs(rate) * 0.005 * RADIUS_M + 1e-9)


@settings(max_examples=40, deadline=None)
@example(late_s=0.078125, jitter=[0.00390625] * 4 + [0.0], rate=6.0)  # 2.07 mrad while a PDO was kept twice
@given(late_s=st.floats(0.01, 0.0755), jitter=st.lists(st.floats(0.0, 0.005), min_size=1, max_size=8),
       rate=st.floats(5.0, 10.0))
def test_a_bus_answering_its_syncs_late_is_paired_at_its_syncs(late_s: float, jitter: list[float],
                                                              rate: float) -> None:
    """can0 SYNCs every 61 ms and its drives answer at once; can1 SYNCs every 89 ms and its drives
    answer ``late_s`` after each SYNC, from the start (a slow drive, a busy bus's arbitration; within
    the SYNC period), each wheel received a little later still by its own jitter (a receive thread's
    wake-up). Every sample is stamped with its SYNC (the driver's stamp); the step reads each
    wheel's newest received sample every 20 ms. Every wheel turns alike, so the heading stays 0:
    while cruising within the alignment's slew (as above), while speeding up within a straight line
    between samples 89 ms apart at ACCEL_RAD_S2 (10 * 0.089^2 / 8 rad at the wheel, 1.7 mrad; can1's
    newest SYNC is up to 89 + 80 ms old, older than a can0 wheel's previous sample: with two samples
    kept, a wheel could not start until they happened to cover it, and lines bridged 150 ms, 4.7
    mrad), and the rover drives from the start. The receive-minus-bus-time
    difference of can1's wheels is their lateness plus the clocks' offset: taken for the clocks'
    offset (a wheel's own least), it stamped can1's samples when they came, and the heading leaned by
    rate * 0.1 m * late_s / 0.6 m while moving (8 mrad at 10 ms and 5 rad/s; 25 at 30 ms).

    Answers up to 85 % of the period after their SYNC (75.5 ms), and the case hypothesis found at
    83 ms (late_s 78 ms, 4 ms jitter, 6 rad/s): it leaned 2.07 mrad while speeding up, more than
    the chord's 1.7 mrad explains, while a PDO read at two steps was kept twice in a wheel's
    history (the clocks' offset, rising OFFSET_DRIFT_S a step, gave it a new measured stamp, and
    the copies pushed out the samples an instant lies between); kept once, 0.76 mrad. A step that
    reads no new sample on a side measures nothing (``measured_at`` 0.0): /odom comes with new data
    from both sides, never the same data stamped anew."""
    odo = odometry()
    mono_minus_wall = 5000.0  # the receive clock (monotonic) against the bus stamps' (wall)
    ramp_s = rate / ACCEL_RAD_S2
    buses = {LEFT: (0.061, 0.0), RIGHT: (0.089, late_s)}  # side: (SYNC period, its drives' lateness)

    def travelled_s(t: float) -> float:  # seconds at full speed: from standing at 1.5 s, at ACCEL_RAD_S2
        t -= 1.5
        return 0.0 if t <= 0.0 else 0.5 * t * t / ramp_s if t < ramp_s else t - 0.5 * ramp_s

    def newest(side: tuple[str, ...], now: float, k: int) -> dict[str, WheelSample]:
        """Each wheel's newest sample received by ``now`` (receive clock)."""
        period, late = buses[side]
        out = {}
        for i, name in enumerate(side):
            came = late + 0.0005 + jitter[(k + i) % len(jitter)]  # after its SYNC
            sync = math.floor((now - mono_minus_wall - came) / period) * period
            out[name] = WheelSample(rate * travelled_s(sync), sync + mono_minus_wall + came, 1, bus_stamp=sync)
        return out

    worst = {"speeding up": 0.0, "cruising": 0.0}
    measured, at = 0, 0.0
    for k in range(1, 200):  # 4 s: standing 1.5 s (the alignment learns the clocks), then driving
        now = mono_minus_wall + 0.5 + k * 0.02 + 0.003
        step = odo.step(newest(LEFT, now, k) | newest(RIGHT, now, k + 3))
        # cruising once every sample a step may interpolate from was of full speed: the step's instant
        # is up to can1's period, lateness and jitter behind (89 + 80 + 5.5 ms), and the sample before
        # it a period older still (hypothesis found 78 ms late straddling the ramp's end at 0.2 s)
        phase = "cruising" if now - mono_minus_wall > 1.5 + ramp_s + 2 * 0.089 + late_s + 0.0055 + 0.02 else "speeding up"
        worst[phase] = max(worst[phase], abs(step.pose.yaw_rad))
        if step.trusted and step.measured_at:
            measured, at = measured + 1, step.measured_at
    assert worst["cruising"] < 2e-4 and worst["speeding up"] < 2e-3, worst
    want_m = rate * travelled_s(at - mono_minus_wall - 0.0005) * RADIUS_M  # the instant of can0's lateness, 0.5 ms
    assert measured > 40 and abs(step.pose.x_m - want_m) < 0.01, (measured, step.pose, want_m)  # from the start
