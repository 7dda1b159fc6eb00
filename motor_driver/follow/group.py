"""A joint trajectory followed on the drives' own SYNC clock: the driver's side of
control_msgs/FollowJointTrajectory, one :class:`TrajectoryGroup` per configured group
(``trajectory_groups``). No rclpy: the node (nodes/actions/follow_trajectory.py) turns goals into
:class:`TrajectoryGoal` and :class:`GoalRun` into results and feedback.

Before anything moves (:meth:`TrajectoryGroup.plan`, on the caller's thread: :mod:`motor_driver.follow.checks`) a goal is refused with
the standard's code (:class:`TrajectoryRejected`): joints unknown, repeated, of another group or
not all of the group's unless ``allow_partial_joints_goal`` (INVALID_JOINTS); points of the wrong
length, not finite, times not strictly increasing, a point or any instant of a segment between two
beyond a joint's limits or its max velocity, a last point with a velocity (unless
``allow_nonzero_velocity_at_trajectory_end``), a tolerance negative other than -1, a joint not usable (its verdict) or
its motion held, a first point (at time 0) further than ``start_tolerance_deg`` from both its joint's
set-point and its measured position (INVALID_GOAL); a header stamp whose trajectory is over already
(OLD_HEADER_TIMESTAMP, the node's).

The clock: the group's thread (``rovercan-follow-<group>``) wakes on each position sample of one of
its drives (:meth:`DriveCache.on_sample`, set by the receive thread: one a SYNC) and sends every
joint's next set-point then, a CSP (or IP) set-point through the drive's command channel
(``stream_position``), so a stop still wins; a SYNC's set-points go out in one write a bus where
the bus is socketcand (``GuardedNetwork.one_write``: a stop sent meanwhile still follows the
set-points handed over before it), and a write that fails ends the goal as a refused set-point does.
The trajectory's time is the monotonic clock's, from
the plan's time zero (:attr:`GoalRun.start_at`: its acceptance, or its header stamp), read at the
sample's reception (its SYNC): the set-point sent is the spline at the next SYNC's time, where the
drive takes it (:class:`motor_driver.follow.trajectory.Spline`). Each set-point advances the plan by
the SYNCs the receive thread counted and closes a share of the gap to the clock (:data:`CLOCK_GAIN`:
a receive thread's jitter is no jump, a SYNC producer off its period no stretch); a SYNC the thread
let go is caught up in the next set-points, each step within its joint's max velocity over one
SYNC period (a CSP drive takes a set-point within one period: :data:`STEP_SHARE`): a thread held
for long (a starved host) makes the plan run late until it has caught up, counted
(:attr:`TrajectoryGroup.stretched_s`), never a jump and never a joint commanded past its limit.
Whatever must happen before
motion (the checks, each joint's switch to streaming) happens before the goal is handed over. A
goal starts from where the group's set-points are at its first set-point (a preempted goal's or a
ramp's, else the drive's last target) with that velocity, so a new goal joins the old without a
jump; the first point at time 0 stands for it. A goal stamped ahead waits: its joints ramp down (a
preempted goal's) or hold until then.

A goal ends: SUCCESSFUL once every joint is within its goal tolerance (position, and the stopped
velocity tolerance) after the last set-point (within the goal time tolerance: else
GOAL_TOLERANCE_VIOLATED; a goal time tolerance of 0 waits without a bound, as
joint_trajectory_controller's update()); PATH_TOLERANCE_VIOLATED when a joint strays further than
its path tolerance before the trajectory's end (after it only the goal tolerance applies), or
refuses a set-point, or its drive's verdict (:mod:`motor_driver.drive.verdict`, the one every part
reads) is not usable: lost, late beyond its staleness bound, faulted, held, stopped;
CANCELED at once on a cancel (the group's thread is woken by it, whether or not a sample comes);
ABORTED with INVALID_GOAL and joint_trajectory_controller's words (:data:`PREEMPTED`) when a newer
goal is handed over. A cancel's or a failure's joints ramp down at ``stop_deceleration_deg_s2`` and
then hold (no more set-points: a CSP drive holds its last target); a joint whose verdict is not
usable is sent nothing more (it holds, or stopped itself).

Owners: the group's thread owns the running goal, the ramp and the tick count; callers hand it goals
and cancels (:meth:`TrajectoryGroup.follow`, :meth:`GoalRun.cancel`) under ``_lock`` and read the
immutable :class:`Progress` and :class:`Outcome` each run publishes; the receive thread only sets the
tick event. An unexpected error in the thread is logged and counted, ends the goal and stops the group;
:meth:`TrajectoryGroup.counters` (errors, late samples, silences) is what /diagnostics says of it.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import can

from can_config.errors import RovercanError
from can_config.model import TrajectoryGroupConfig
from motor_driver.bus.adapters import GuardedNetwork, HeldFramesLost
from motor_driver.drive import Drive
from motor_driver.follow.checks import GoalChecks
from motor_driver.follow.goal import (
    PREEMPTED,
    GoalRun,
    Outcome,
    Plan,
    Progress,
    TrajectoryCode,
    TrajectoryGoal,
    refuse,
)
from motor_driver.follow.trajectory import Knot, Spline

logger = logging.getLogger(__name__)

#: A clock sample older than this share of the SYNC period when its set-points go out is late (a
#: count for /diagnostics): its set-points are then the plan at the SYNC after the next, the first
#: they can still reach. Its age is counted from its SYNC (the sample's stamp: when it measured).
#: A sample with a newer one behind it is let go for that one.
LATE_SHARE = 0.5
#: How long close() waits for the group's thread.
JOIN_S = 2.0
#: How long a goal's preparation waits for its joints' other operations (an enable under way) to end.
BUSY_WAIT_S = 5.0
#: The plan's time advances from one set-point to the next only as far as every joint's step stays
#: within its max velocity over one SYNC period (a CSP drive takes a set-point within one period, so
#: a longer step commands the joint faster than its limit; stream_position's guard, two periods'
#: travel, is the drive's last line): a thread that missed SYNCs (a starved host) catches up as fast
#: as its joints may move, and where the plan itself runs near their limit it runs late instead,
#: counted (stretched_s), never by a jump. GUARD_PASSES: the tries at a shorter advance (the spline
#: is smooth: a share of the way is about that share of the step); GUARD_HALVINGS: then halvings.
STEP_SHARE = 1.0
GUARD_PASSES = 4
GUARD_HALVINGS = 12
#: The first set-point of a goal is the plan at most this many SYNC periods from its join.
JOIN_PERIODS = 2
#: How much of the gap between the SYNCs counted and the monotonic clock (the sample's reception) one
#: set-point closes: the plan keeps the clock's time (a SYNC producer slower or faster than its period
#: does not stretch it), while a receive thread's jitter moves a step by this share of it only.
CLOCK_GAIN = 0.5
#: The longest wait for a sample, in SYNC periods, before the group looks at its drives' verdicts
#: (a silence): a goal whose joints fall silent ends within their staleness bound plus this.
SILENCE_PERIODS = 2.0


@dataclass
class _Running:
    """The group thread's running goal (its own, never shared)."""

    run: GoalRun
    joints: tuple[Drive, ...]
    spline: Spline | None = None  # built at its first set-point, from where the set-points are then
    offset_s: float = 0.0  # the plan's time of the spline's start
    last: tuple[object, int] = (None, 0)  # the clock drive and its sample count at the last set-point
    last_t: float = 0.0  # the plan time of the last set-point
    behind_s: float = 0.0  # how far that ran behind the plan's time (each step held to the joints' limit)
    final_sent: bool = False
    last_desired: tuple[tuple[float, float, float], ...] = ()
    seen: list[int] = field(default_factory=list)  # each joint's position sample count when it last changed
    quiet: list[int] = field(default_factory=list)  # the clock's SYNCs since then


class TrajectoryGroup:
    """The joints of one ``trajectory_groups`` entry, following one goal at a time."""

    def __init__(self, config: TrajectoryGroupConfig, drives: Mapping[str, Drive]) -> None:
        self.config = config
        self.name = config.name
        self.drives = {j: drives[j] for j in config.joints}
        first = self.drives[config.joints[0]]
        self.period_s = first.cache.sync_period_s
        self.errors = 0  # unexpected errors of the thread (each ended a goal in a stop)
        self.late = 0  # samples this thread took later than LATE_SHARE of a period (aimed a SYNC further)
        #: the most (s) a plan ran behind its time because no joint may step further than its max velocity
        #: over one SYNC period to catch up (this thread held: a starved host): late, never by a jump
        self.stretched_s = 0.0
        self.silences = 0  # waits for a sample that ended without one (SILENCE_PERIODS)
        self._lock = threading.Lock()
        self._pending: GoalRun | None = None
        self._wake = threading.Event()
        self._tick = threading.Event()
        self._closed = False
        # the thread's own
        self._running: _Running | None = None
        #: joint -> (position, velocity, rebased) ramping down; rebased: its next set-point may jump to where the
        #: joint was measured (an abort's ramp: _to_ramp), beyond the step guard a set-point's stream keeps
        self._ramp: dict[str, tuple[float, float, bool]] = {}
        self._clock: Drive | None = None
        self._clock_seq = -1
        self._silences = 0  # the clock's waits in a row that ended without a sample
        self._checks = GoalChecks(config, self.drives)
        #: the buses (name, network) whose set-points of one SYNC go out in one write (GuardedNetwork.one_write)
        self._networks = tuple({id(d.network): (d.config.bus, d.network) for d in self.drives.values()
                                if isinstance(d.network, GuardedNetwork)}.values())
        self._thread = threading.Thread(target=self._loop, name=f"rovercan-follow-{self.name}", daemon=True)
        self._thread.start()

    # ------------------------------------------------------------------ callers
    @property
    def alive(self) -> bool:
        """The group's thread runs (it ends only on close)."""
        return self._thread.is_alive()

    @property
    def busy(self) -> bool:
        """A goal runs, waits to start, or its joints ramp down."""
        return self._running is not None or self._pending is not None or bool(self._ramp)

    def counters(self) -> dict[str, float]:
        """The thread's background counts, for /diagnostics."""
        return {"errors": self.errors, "late samples": self.late, "silences": self.silences,
                "plan behind at most (s)": round(self.stretched_s, 3)}

    def follow(self, goal: TrajectoryGoal, cancelled: Callable[[], bool] | None = None) -> GoalRun:
        """Check ``goal`` (:class:`TrajectoryRejected` with its code: nothing moved), switch its
        joints to streaming where they are not, and hand it over (:meth:`start`), its time zero
        then. Returns once handed over (a mode switch may wait); the run says how it ends.
        ``cancelled``: asked right before the handover; True ends the run "cancelled before it
        started", and the goal running (or pending) goes on untouched."""
        plan = self.plan(goal)
        asked = cancelled or (lambda: False)
        if not asked():  # a goal cancelled before its start switches no mode
            self.prepare(goal.joints)
        return self.start(plan, time.monotonic() + goal.start_delay_s, cancelled=asked())

    def prepare(self, joints: Sequence[str]) -> None:
        """Each joint free of another operation of this driver's (an enable, a mode switch under way:
        it would refuse the set-points; waited for up to :data:`BUSY_WAIT_S`, else refused) and
        switched to CSP (or IP) where it is not yet, holding where it stands; on the caller's thread,
        which may wait on the drives: before a goal is accepted."""
        for name in joints:
            drive = self.drives[name]
            if busy := self._wait_free(drive):
                raise refuse(TrajectoryCode.INVALID_GOAL, f"{name}: busy with {busy} for {BUSY_WAIT_S:g} s; send the"
                              " goal again when it is done; nothing moved")
            self._prepare(drive)

    def start(self, plan: Plan, start_at: float, cancelled: bool = False) -> GoalRun:
        """Hand a checked plan (its joints streaming: :meth:`prepare`) to the group's thread, which
        takes it at once: the goal running (or pending) ends INVALID_GOAL (:data:`PREEMPTED`). ``start_at``:
        the plan's time zero on the monotonic clock. ``cancelled``: the run ends "cancelled before it
        started" and the goal running goes on."""
        run = GoalRun(plan, start_at, wake=self._tick.set)
        stop = cancelled
        with self._lock:
            if self._closed:
                raise refuse(TrajectoryCode.INVALID_GOAL, f"trajectory group {self.name}: the driver shut down")
            if not self._thread.is_alive():  # a goal handed to no thread would never end
                raise refuse(TrajectoryCode.INVALID_GOAL, f"trajectory group {self.name}: its thread has ended"
                             " (see the log); restart the driver")
            if stop:
                run.finish(Outcome(TrajectoryCode.SUCCESSFUL, "cancelled before it started", canceled=True))
                return run
            older, self._pending = self._pending, run
        if older is not None:
            older.finish(Outcome(TrajectoryCode.INVALID_GOAL, PREEMPTED))
        self._wake.set()
        self._tick.set()  # a thread waiting for the clock takes it now
        return run

    @staticmethod
    def _wait_free(drive: Drive) -> str | None:
        """Until no other operation runs on the drive (looked at with each statusword), at most
        :data:`BUSY_WAIT_S`; the one still under way then, else None."""
        channel = drive.channel
        if channel.busy:
            drive.cache.wait_until(lambda: not channel.busy, BUSY_WAIT_S)
        return channel.busy

    @staticmethod
    def _prepare(drive: Drive) -> None:
        """A joint not streaming yet: switched to CSP (or IP), holding where it stands, on this (the
        caller's) thread, which may wait; the group's thread never switches modes."""
        drive.motion.start_stream()

    def close(self) -> None:
        """The thread ends (after its tick); a goal running ends with 'the driver shut down'. Idempotent."""
        with self._lock:
            self._closed = True
        self._wake.set()
        self._tick.set()
        if self._thread is not threading.current_thread():
            self._thread.join(JOIN_S)

    @property
    def ramping(self) -> bool:
        """Some joint is still ramping down (a cancelled or failed goal's)."""
        return bool(self._ramp)

    def plan(self, goal: TrajectoryGoal) -> Plan:
        """``goal`` checked against the group, the joints' limits and their drives (nothing sent)."""
        return self._checks.plan(goal, self._reference)

    def _reference(self, joints: Sequence[str]) -> tuple[Knot, ...]:
        """Where each joint's set-points are now, and how fast they move (read from any thread: a
        ramp's set-point (a preempted goal's joints ramp down while a new goal waits for its stamp:
        the ramp's is the newer), a running goal's last set-point, else the drive's last target or
        its position)."""
        running, ramp = self._running, dict(self._ramp)
        desired = dict(zip((d.name for d in running.joints), running.last_desired, strict=False)) if running else {}
        out: list[Knot] = []
        for name in joints:
            if name in ramp:
                p, v, rebased = ramp[name]
                if rebased:  # its step back to the measured joint not sent yet: the drive holds its last target
                    drive = self.drives[name]
                    p = drive.cache.scale.counts_to_deg(drive.channel.target_counts)
                out.append((p, v, 0.0))
            elif name in desired:
                p, v, a = desired[name]
                out.append((p, v, a))
            else:
                drive = self.drives[name]
                held = drive.motion.streaming()
                position = drive.cache.scale.counts_to_deg(drive.channel.target_counts) if held else drive.cache.angle_deg
                out.append((position, 0.0, 0.0))
        return tuple(out)

    # ------------------------------------------------------------------ the group's thread
    def _loop(self) -> None:
        while True:
            with self._lock:
                closed = self._closed
            if closed:
                self._shut_down()
                return
            if self._running is None and not self._ramp and self._pending is None:
                self._wake.wait()
                self._wake.clear()
                continue
            try:
                self._cycle()
            except Exception as err:  # supervised: logged, counted, the goal ended in a stop
                self.errors += 1
                logger.exception("trajectory group %s: unexpected error; the goal ends and the group stops", self.name)
                self._fail(TrajectoryCode.PATH_TOLERANCE_VIOLATED, f"trajectory group {self.name}: internal error {err!r}")

    def _cycle(self) -> None:
        """One SYNC: take a new goal or a cancel, then every joint's next set-point."""
        with self._lock:
            pending, self._pending = self._pending, None
        if pending is not None:
            try:
                self._start(pending)
            except Exception as err:  # the new goal ends too, not only the one running
                pending.finish(Outcome(TrajectoryCode.PATH_TOLERANCE_VIOLATED,
                                       f"trajectory group {self.name}: the goal could not start ({err!r})"))
                raise
        running = self._running
        if running is not None and running.run.cancel_requested:  # at once, sample or not
            running.run.finish(Outcome(TrajectoryCode.SUCCESSFUL, "cancelled: the joints ramp down and hold",
                                       canceled=True))
            self._to_ramp(running)
        ticked = self._wait_tick()
        if ticked is None:  # a new goal, a cancel or the shutdown came first, or the sample came too late
            return
        if not ticked:
            self.silences += 1
            self._silences += 1
            self._judge_silence()
            return
        self._silences = 0
        # this SYNC's set-points, one write a bus
        with GuardedNetwork.each_one_write(self._networks) as failed:
            if self._running is not None and self._clock is not None:
                self._step(self._running, self._clock)
            self._step_ramp()
        unexpected: Exception | None = None
        for bus, error in failed:
            if isinstance(error, (can.CanError, OSError)):
                self._not_sent(bus, error)
            else:  # a hook's, a receive thread dead otherwise: the loop's handler says it
                unexpected = unexpected or error
        if unexpected is not None:
            raise unexpected

    def _not_sent(self, bus: str, err: Exception) -> None:
        """The set-points of ``bus`` held for this SYNC were not written, or the bus was found broken
        after they were: the goal ends as a refused set-point ends it (or the ramp of that bus's joints)."""
        why = (f"bus {bus}: set-points not sent: the bus is gone ({err})" if isinstance(err, HeldFramesLost)
               else f"bus {bus}: the bus is gone after this SYNC's set-points ({err})")
        if self._running is not None:
            self._fail(TrajectoryCode.PATH_TOLERANCE_VIOLATED, f"{why}; the group stops")
        else:
            logger.warning("trajectory group %s: %s; its joints' stop ramp ends (they hold, or stop"
                           " themselves)", self.name, why)
            for name in [n for n in self._ramp if self.drives[n].config.bus == bus]:
                del self._ramp[name]

    def _start(self, run: GoalRun) -> None:
        joints = run.plan.goal.joints
        start = None if run.cancel_requested else self._reference(joints)  # with the running goal's acceleration
        old = self._running
        if old is not None:  # its joints ramp from its last set-point until the new spline takes them
            old.run.finish(Outcome(TrajectoryCode.INVALID_GOAL, PREEMPTED))
            self._to_ramp(old)
        if start is None:  # cancelled before the thread took it: the older goal was preempted all the same,
            # at the newer one's acceptance (joint_trajectory_controller's preempt_active_goal); its joints
            # ramp down and hold
            run.finish(Outcome(TrajectoryCode.SUCCESSFUL, "cancelled before it started", canceled=True))
            return
        drives = tuple(self.drives[j] for j in joints)
        self._running = _Running(run, drives, last_desired=tuple((p, v or 0.0, a or 0.0) for p, v, a in start),
                                 seen=[d.cache.position_seq for d in drives], quiet=[0] * len(drives))
        self._set_clock(self._running.joints[0])  # the first joint: its sample comes early after the SYNC

    def _set_clock(self, drive: Drive) -> None:
        if self._clock is drive:
            return
        if self._clock is not None:
            self._clock.cache.on_sample(None)
        self._clock = drive
        self._clock_seq = drive.cache.position_seq
        drive.cache.on_sample(self._tick.set)

    def _wait_tick(self) -> bool | None:
        """Until the clock drive's next position sample (True), for :data:`SILENCE_PERIODS` without
        one (False), or until a new goal, a cancel, the shutdown or a sample taken too late (None)."""
        clock = self._clock
        if clock is None:
            return False
        limit = SILENCE_PERIODS * self.period_s
        while clock.cache.position_seq == self._clock_seq:
            if not self._tick.wait(limit):
                return False
            self._tick.clear()
            with self._lock:
                if self._closed or self._pending is not None:
                    return None
            running = self._running
            if running is not None and running.run.cancel_requested:
                return None
        self._clock_seq = seq = clock.cache.position_seq
        if self._age(clock) > LATE_SHARE * self.period_s:
            self.late += 1
        return None if clock.cache.position_seq != seq else True

    @staticmethod
    def _age(clock: Drive) -> float:
        """How long ago the clock's sample was measured: by its stamp (its SYNC's, on the bus) where
        that is this host's clock (SocketCAN, a local socketcand daemon: a receive thread that was
        late itself does not hide it), else since the receive thread took it."""
        rx = clock.cache.received
        on_bus = time.time() - rx.stamp
        return on_bus if 0.0 <= on_bus < 1.0 else time.monotonic() - rx.rx_monotonic

    def _taken_at(self, clock: Drive) -> tuple[float, bool]:
        """(the monotonic time of the SYNC this step's set-points are taken at, whether it is the
        bus's): the clock sample's SYNC (its stamp, on this host's clock) plus the periods to the
        first SYNC they still reach (one, or the one after when sent later than LATE_SHARE into the
        period, or later still after a longer wait: a late thread shifts no plan); where the stamp
        is another clock's, its reception plus a period (False)."""
        rx = clock.cache.received
        wall, now = time.time(), time.monotonic()
        age = wall - rx.stamp
        if not 0.0 <= age < 1.0:
            return rx.rx_monotonic + self.period_s, False
        return now - age + (math.floor(age / self.period_s + LATE_SHARE) + 1) * self.period_s, True

    def _judge_silence(self) -> None:
        """No sample from the clock: a joint whose verdict is not usable (lost, or late beyond its
        staleness bound: the verdict's judgement, not this thread's clock) ends the goal; after a
        second silence the clock moves to another joint."""
        running = self._running
        if running is not None:
            for drive in running.joints:
                if (why := self._unusable(drive)) is not None:
                    self._fail(TrajectoryCode.PATH_TOLERANCE_VIOLATED, f"{drive.name}: {why} mid-goal; the group stops")
                    break
        streamed = [d for d in self.drives.values() if d.name in self._ramp or (
            self._running is not None and d in self._running.joints)]
        live = [d for d in streamed if self._unusable(d) is None]
        if not live:
            if self._running is None:
                self._ramp.clear()  # nothing can be sent: what is left holds, or stopped by itself
            return
        others = [d for d in live if d is not self._clock]
        if self._silences > 1 and others:
            self._set_clock(others[-1])

    @staticmethod
    def _unusable(drive: Drive) -> str | None:
        """Why the joint may not be driven: its verdict (the one every part reads, judged once per
        input change and read here as a value), else None."""
        verdict = drive.power.verdict()
        return None if verdict.usable else f"{verdict.condition.value}: {verdict.cause}" + (
            f"; {verdict.helps}" if verdict.helps else "")

    def _step(self, running: _Running, clock: Drive) -> None:
        """This SYNC's set-points: the plan at the time of the SYNC where the drives take them. The
        plan's time, from its time zero: that SYNC's, on the bus's clock (the clock sample's SYNC
        stamp: no receive thread's jitter, no late thread's wait moves it); where the bus stamps
        another clock, the monotonic clock's at the first sample, then the SYNCs counted by the
        clock's samples (one a SYNC, counted by the receive thread: a sample this thread let go
        still counts), closing a share of the gap to the clock each step."""
        seq = clock.cache.position_seq
        taken_at, on_bus = self._taken_at(clock)
        now = taken_at - running.run.start_at
        if running.spline is None:
            if now <= 0.0:
                self._hold(running)
                return  # stamped ahead: its joints hold (or ramp down) until then
            self._join(running, now - self.period_s)
            t = self._guarded(running, min(now, running.offset_s + JOIN_PERIODS * self.period_s))
        else:
            drive, last_seq = running.last
            counted = running.last_t + (seq - last_seq if drive is clock else 1) * self.period_s
            t = now if on_bus else counted + CLOCK_GAIN * (now - counted)
            wanted = max(t, running.last_t)
            if running.final_sent:  # the goal time runs from the last set-point, late or not, at the clock's pace
                t = max(running.last_t, wanted - running.behind_s)
            else:
                t = self._guarded(running, wanted)
                self.stretched_s = max(self.stretched_s, wanted - t)  # behind the plan, held to the limit
                assert running.spline is not None
                # the last set-point is the plan's end, and however late it goes out the goal time runs from it
                t = min(t, running.offset_s + running.spline.end_s)
                running.behind_s = wanted - t
        running.last, running.last_t = (clock, seq), t
        spline = running.spline
        assert spline is not None
        local = t - running.offset_s
        actual = tuple((d.cache.angle_deg, d.cache.scale.counts_s_to_deg_s(d.cache.received.velocity_counts_s))
                       for d in running.joints)
        if (error := self._strayed(running, actual)) is not None:
            self._fail(TrajectoryCode.PATH_TOLERANCE_VIOLATED, error, measured=True)
            return
        if running.final_sent:
            self._settle(running, actual, local - spline.end_s)
            return
        # this SYNC's measurement against the set-point in force at it (sent the tick before, taken by
        # the drive at this SYNC): the trajectory at its time, as joint_trajectory_controller pairs them
        running.run.report(Progress(max(t - self.period_s, 0.0), running.run.plan.goal.joints, running.last_desired,
                                    actual))
        running.final_sent = local >= spline.end_s - 1e-9 * self.period_s
        desired = spline.sample(min(local, spline.end_s))
        for drive, (p, _, _) in zip(running.joints, desired, strict=True):
            try:
                drive.stream_position(p)
            except RovercanError as err:
                self._fail(TrajectoryCode.PATH_TOLERANCE_VIOLATED, f"{drive.name}: set-point refused mid-goal: {err};"
                           " the group stops")
                return
        running.last_desired = desired

    def _guarded(self, running: _Running, t: float) -> float:
        """``t``, or as far toward it from the last set-points' time as every joint may step within
        one SYNC period at its max velocity (STEP_SHARE): a share of the way by the step's share
        (GUARD_PASSES tries), then halving between the last time known within and the nearest known
        beyond (GUARD_HALVINGS): the plan advances wherever the spline is continuous."""
        if running.spline is None or t <= running.last_t:
            return t
        within, beyond = running.last_t, t
        candidate = t
        for _ in range(GUARD_PASSES):
            share = self._step_share(running, candidate)
            if share >= 1.0:
                return candidate
            beyond = candidate
            candidate = within + (candidate - within) * share * (1.0 - 1e-6)
        for _ in range(GUARD_HALVINGS):
            middle = 0.5 * (within + beyond)
            if self._step_share(running, middle) >= 1.0:
                within = middle
            else:
                beyond = middle
        return within

    def _step_share(self, running: _Running, t: float) -> float:
        """The share of the step to the plan at ``t`` that every joint may take in one SYNC period
        (at least 1: all of it)."""
        spline = running.spline
        assert spline is not None
        desired = spline.sample(min(t - running.offset_s, spline.end_s))
        return min((STEP_SHARE * self.period_s * d.config.max_velocity_deg_s / abs(p - last[0])
                    for d, (p, _, _), last in zip(running.joints, desired, running.last_desired, strict=True)
                    if p != last[0]), default=math.inf)

    def _hold(self, running: _Running) -> None:
        """A goal waiting for its stamp: its joints not ramping down hold their set-point, one a SYNC."""
        for drive, (p, _, _) in zip(running.joints, running.last_desired, strict=True):
            if drive.name not in self._ramp:
                try:
                    drive.stream_position(p)
                except RovercanError as err:
                    self._fail(TrajectoryCode.PATH_TOLERANCE_VIOLATED, f"{drive.name}: set-point refused while the goal"
                               f" waits for its start: {err}; the group stops")
                    return

    def _join(self, running: _Running, now_s: float) -> None:
        """The goal's spline from where its joints' set-points are now (a preempted goal's or a ramp's,
        taken off the ramp), standing for the plan's time ``now_s`` (its first knot's time shortened
        by it, so that the plan keeps its time from acceptance)."""
        plan = running.run.plan
        start = self._reference(plan.goal.joints)
        for name in plan.goal.joints:
            self._ramp.pop(name, None)
        offset = min(max(now_s, 0.0), 0.5 * plan.times_s[0])
        running.offset_s = offset
        running.spline = Spline((0.0, *(t - offset for t in plan.times_s)), (start, *plan.knots))
        running.last_desired = tuple((p, v or 0.0, a or 0.0) for p, v, a in start)
        running.last_t = offset

    def _strayed(self, running: _Running, actual: tuple[tuple[float, float], ...]) -> str | None:
        """The first joint outside its path tolerance (from the set-point it is following; until the
        trajectory's end, as joint_trajectory_controller's before_last_point), lost, or
        without a position sample for more than its stale_after_syncs of the clock's SYNCs (counted,
        not timed: a starved process catches up on the samples in order)."""
        for i, (drive, tol, (p, v, _), (ap, av)) in enumerate(zip(running.joints, running.run.plan.path,
                                                                  running.last_desired, actual, strict=True)):
            seq = drive.cache.position_seq
            running.quiet[i] = 0 if seq != running.seen[i] else running.quiet[i] + 1
            running.seen[i] = seq
            if running.quiet[i] > drive.config.stale_after_syncs:
                return (f"{drive.name}: no position sample for {running.quiet[i]} SYNCs (stale_after_syncs="
                        f"{drive.config.stale_after_syncs}) mid-goal; the group stops")
            # while set-points go out, each is refused with the verdict's cause by the drive's own
            # check (stream_position: late, lost, not enabled); after the last one it is read here
            if running.final_sent:  # past the end only the goal tolerance and the goal time apply
                if (why := self._unusable(drive)) is not None:  # (joint_trajectory_controller: before_last_point)
                    return f"{drive.name}: {why} mid-goal; the group stops"
                continue
            if tol.position_deg > 0 and abs(ap - p) > tol.position_deg:
                return (f"{drive.name}: {abs(ap - p):.3f} deg from the trajectory ({ap:.3f} deg, set-point {p:.3f});"
                        f" path tolerance {tol.position_deg:g} deg")
            if tol.velocity_deg_s > 0 and abs(av - v) > tol.velocity_deg_s:
                return (f"{drive.name}: {av:.2f} deg/s against {v:.2f} deg/s on the trajectory; path velocity"
                        f" tolerance {tol.velocity_deg_s:g} deg/s")
        return None

    def _settle(self, running: _Running, actual: tuple[tuple[float, float], ...], after_s: float) -> None:
        """After the last set-point: success once every joint is within its goal tolerance."""
        plan = running.run.plan
        far = None
        for drive, tol, (p, _, _), (ap, av) in zip(running.joints, plan.final, running.last_desired, actual,
                                                   strict=True):
            if tol.position_deg > 0 and abs(ap - p) > tol.position_deg:
                far = f"{drive.name}: {abs(ap - p):.3f} deg from the goal {p:.3f} deg; goal tolerance {tol.position_deg:g} deg"
                break
            if tol.velocity_deg_s > 0 and abs(av) > tol.velocity_deg_s:
                far = f"{drive.name}: still moving at {av:.2f} deg/s; goal velocity tolerance {tol.velocity_deg_s:g} deg/s"
                break
        running.run.report(Progress(plan.times_s[-1], plan.goal.joints, running.last_desired, actual))
        if far is None:
            self._running = None
            running.run.finish(Outcome(TrajectoryCode.SUCCESSFUL, "at the goal"))
        elif 0.0 < plan.goal_time_s < after_s:  # 0: no bound (joint_trajectory_controller's update())
            running.run.finish(Outcome(TrajectoryCode.GOAL_TOLERANCE_VIOLATED,
                                       f"{far}, {after_s:.2f} s after the trajectory's end (goal time tolerance"
                                       f" {plan.goal_time_s:g} s)"))
            self._to_ramp(running, measured=True)  # held where they are, not pushed on toward the goal

    # ------------------------------------------------------------------ stopping
    def _fail(self, code: TrajectoryCode, message: str, *, measured: bool = False) -> None:
        """The goal aborted, its joints ramped down (``measured``: judged on this SYNC's samples, which
        :meth:`_to_ramp` may ramp from)."""
        running = self._running
        if running is None:
            self._ramp.clear()
            return
        logger.warning("trajectory group %s: goal aborted: %s", self.name, message)
        running.run.finish(Outcome(code, message))
        self._to_ramp(running, measured=measured)

    def _to_ramp(self, running: _Running, keep: Sequence[str] = (), *, measured: bool = False) -> None:
        """A goal's joints (but ``keep``, which a new goal takes) ramp down: from their last set-point
        (a cancel, a preemption: the joints were following it), or, after a tolerance missed on this
        SYNC's samples (``measured``), from each joint's measured position and velocity (the velocity
        within its limit) where its sample is this SYNC's, as joint_trajectory_controller holds the
        measured state: a joint that strayed (blocked, slipping) is not driven on into what held it.
        That ramp's first set-point may step back to the joint beyond the stream's step guard; a joint
        without a sample this SYNC ramps from its set-point (an old sample is no place to jump to)."""
        for i, (drive, (p, v, _)) in enumerate(zip(running.joints, running.last_desired, strict=True)):
            if drive.name in keep or self._unusable(drive) is not None:
                continue
            if measured and running.quiet[i] == 0:
                cache, top = drive.cache, drive.config.max_velocity_deg_s
                velocity = cache.scale.counts_s_to_deg_s(cache.received.velocity_counts_s)
                self._ramp[drive.name] = (cache.angle_deg, max(-top, min(top, velocity)), True)
            else:
                self._ramp[drive.name] = (p, v, False)
        if self._running is running:
            self._running = None

    def _step_ramp(self) -> None:
        """One set-point of each ramping joint: the velocity cut by the stop deceleration a period,
        clamped to the joint's limits; a joint at rest leaves the ramp (it holds)."""
        dv = self.config.stop_deceleration_deg_s2 * self.period_s
        for name, (p, v, rebased) in list(self._ramp.items()):
            drive = self.drives[name]
            slower = math.copysign(max(abs(v) - dv, 0.0), v)
            position = p + (v + slower) / 2 * self.period_s
            cfg = drive.config
            if cfg.min_deg is not None and cfg.max_deg is not None:
                position = min(max(position, cfg.min_deg), cfg.max_deg)
            try:
                drive.stream_position(position, max_step_deg=math.inf if rebased else None)
            except RovercanError as err:
                logger.warning("trajectory group %s: %s's stop ramp refused (%s); it holds or stopped itself",
                               self.name, name, err)
                slower = 0.0
            if slower == 0.0:
                del self._ramp[name]
                self._held_at(name, position)
            else:
                self._ramp[name] = (position, slower, False)

    def _held_at(self, name: str, position: float) -> None:
        """A joint whose ramp ended holds ``position``: a goal waiting for its stamp holds it there
        (its last set-point was the preempted goal's, from before the ramp)."""
        running = self._running
        if running is not None and running.spline is None:
            running.last_desired = tuple((position, 0.0, 0.0) if d.name == name else knot
                                         for d, knot in zip(running.joints, running.last_desired, strict=True))

    def _shut_down(self) -> None:
        if self._clock is not None:
            self._clock.cache.on_sample(None)
        with self._lock:
            pending, self._pending = self._pending, None
        for run in (pending, self._running.run if self._running else None):
            if run is not None:
                run.finish(Outcome(TrajectoryCode.INVALID_GOAL, f"trajectory group {self.name}: the driver shut down"))
        self._running = None


def groups_of(configs: Sequence[TrajectoryGroupConfig], drives: Mapping[str, Drive]) -> dict[str, TrajectoryGroup]:
    """A group for each config whose joints are all among ``drives`` (a node serving one joint has none)."""
    return {c.name: TrajectoryGroup(c, drives) for c in configs if all(j in drives for j in c.joints)}
