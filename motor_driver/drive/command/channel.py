"""The command channel of one drive: the only way a controlword or a set-point leaves the process.

Owner: this object, under ``_lock``: the controlword last sent (``_cw``), the position target,
the generation counter, the stop that preempted (``_preempted``), the busy registry, the
set-point handshake, and what is commanded (enabled by this driver, a live velocity command).
Command threads, the supervisor (watchdog, limit guard, the stop on losing a drive) and the
receive thread (the handshake's reply) all come here; nobody else builds such a frame.

The rule, kept by construction:

- ``_lock`` is held only to decide and to send one PDO. Never an SDO, a sleep or a wait for
  the drive. An operation that waits (enable, homing, recover, a mode switch, a target written
  by SDO) registers in the busy registry instead, under a token of its own; commands from
  others are refused at once meanwhile. An operation removes only its own entry; a nested
  operation (homing's enable) runs under its caller's token and generation.
- A stop's decision and its frame are one critical section that bumps the generation. Every
  other frame leaves only if, under the same lock, the operation it belongs to was not
  preempted and this driver's last controlword is still Enable Operation (for motion frames):
  so after a stop nothing but a later, explicitly requested enable reaches the drive.
- A controlword the drive takes only by SDO (no RPDO maps it) is decided under the lock and
  written after it; a stop decided meanwhile is written again after such a write.
- While motion is held (:meth:`CommandChannel.hold`, with its reason: the lifecycle node
  inactive), every operation and command is refused with that reason before anything is sent,
  and an operation under way ends at its next step; the stops (and a halt) are still taken.
  :meth:`CommandChannel.admit` is that one verdict: the drive's other ways in (a mode switch
  already done, a tool's SDO write, the drive system) ask it too, for the reason to be the one said.

``set_hook`` is the seam for tests that force an interleaving: the hook is called at named
points, some inside the critical section (``"<what>: decided"``) and where a caller finds the
lock taken (``"<what>: waiting for the lock"``), so a test can prove a competitor is held off.
"""

from __future__ import annotations

import logging
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from typing import NamedTuple

from can_config.errors import CommandRejected, DriveStateError
from can_config.objects import OD, OperationMode
from motor_driver.drive.command.busy import BusyRegistry, Op
from motor_driver.drive.command.setpoint import SetpointHandshake
from motor_driver.drive.constants import COMMAND_LOCK_WAIT_S, ENABLED_CW_MASK
from motor_driver.protocol.cia402 import CW, Command, controlword
from motor_driver.protocol.pdo import PdoMap, PdoPlan, encode_rpdo

logger = logging.getLogger(__name__)

#: The controlwords of the stops: the channel re-sends one after a controlword written by SDO.
STOP_WORDS = frozenset({int(Command.QUICK_STOP), int(Command.SHUTDOWN), int(Command.DISABLE_VOLTAGE)})
#: A streamed set-point's controlword and target object by mode; enum members read once here, not per set-point
_STREAM_CW_TARGET = {OperationMode.CYCLIC_SYNC_POSITION: (int(Command.ENABLE_OPERATION), OD.TARGET_POSITION),
                     OperationMode.INTERPOLATED_POSITION: (Command.ENABLE_OPERATION | CW.NEW_SETPOINT, OD.INTERPOLATION_DATA)}
_CONTROLWORD = OD.CONTROLWORD


class CommandChannel:
    """Decides and sends every frame carrying a controlword or a set-point of one drive."""

    def __init__(self, name: str, node_id: int, plan: PdoPlan, send: Callable[[int, bytes], None],
                 write_cw_sdo: Callable[[int], None], wake: Callable[[], None],
                 on_live: Callable[[], None] = lambda: None) -> None:
        self.name, self.node_id = name, node_id
        self._plan = plan
        self._send = send
        self._write_cw_sdo = write_cw_sdo
        self._wake = wake
        #: a velocity or torque command went live (never waits): the supervisor's wake
        self.on_live = on_live
        self._lock = threading.Lock()
        # read by anyone, written here only (tests/test_ownership.py), under _lock
        self.cw = 0
        self.target_counts = 0
        self.stream_velocity_counts_s = 0
        self.last_enable_sent = 0.0  # when this driver last sent Enable Operation (monotonic), 0.0 never
        self.generation = 0
        self._preempted: tuple[int, str] = (0, "")
        self._busy = BusyRegistry()
        self.closed = False
        self.held = ""  # why no motion is taken (the stops are), "" while it is
        self.was_enabled = False
        self.enables = 0  # enables completed: a reader that saw fewer has had an enable since
        self.velocity_commanded = False
        self.last_velocity_cmd = 0.0
        self._handshake = SetpointHandshake(self._send_setpoint, self._clear_setpoint)
        self._hook: Callable[[str], None] | None = None
        #: each streamed mode: its set-point's frame (:class:`StreamFrame`), judged once from the plan (frozen)
        self._streams = {mode: StreamFrame.of(plan, cw, target) for mode, (cw, target) in _STREAM_CW_TARGET.items()}

    # ------------------------------------------------------------------ reading
    @property
    def busy(self) -> str | None:
        """The oldest operation under way, or None."""
        return self._busy.oldest

    @property
    def enabling(self) -> bool:
        """An enable is under way (its own, or under a parent operation such as homing)."""
        return self._busy.under_way("enable")

    @property
    def stopped_by(self) -> str:
        """The newest stop of this driver's (who and why), "" none yet."""
        return self._preempted[1]

    @property
    def stop_mark(self) -> int:
        """Where the newest stop (or hold) stands: a caller that saw another value before has
        had a stop since."""
        return self._preempted[0]

    def stopped_unsent(self, by: str) -> None:
        """A stop for a drive that cannot take one now (it is being configured again after a
        reset, not enabled): nothing is sent, and it is not enabled again after its configuration."""
        with self._lock:
            self.generation += 1
            self._preempted = (self.generation, by)
            self.was_enabled = False
        self._wake()

    @property
    def handshake_idle(self) -> bool:
        return self._handshake.idle

    @property
    def newest_move_counts(self) -> int | None:
        """The newest profile-position target commanded (parked or sent; None: none yet), any thread:
        a move's watcher tells from it that another command set the joint's target since."""
        return self._handshake.newest

    @property
    def rpdo_ids(self) -> frozenset[int]:
        """The CAN IDs of this drive's RPDOs (the frames a command of it sends by PDO)."""
        return frozenset(pdo.cob_id for pdo in self._plan.rpdos)

    @property
    def halted(self) -> bool:
        """This driver's last controlword carries halt (bit 8), any thread: a halt stands (the next
        profile-position target, an enable or a stop clears it)."""
        return bool(self.cw & CW.HALT)

    def enabled_by_us(self, now: float, within_s: float) -> bool:
        """This driver's last controlword was Enable Operation, an enable of its own is under way (a
        drive's Operation Enabled reaches a starved process after its enable's steps, however late),
        or it sent one within ``within_s``."""
        enable = int(Command.ENABLE_OPERATION)
        sent = self.last_enable_sent
        return self.cw & enable == enable or self.enabling or (sent > 0.0 and now - sent < within_s)

    def set_hook(self, hook: Callable[[str], None] | None) -> None:
        """Tests only: ``hook(point)`` at the named points of the channel (see the module doc)."""
        self._hook = hook

    def point(self, name: str) -> None:
        if self._hook is not None:
            self._hook(name)

    # ------------------------------------------------------------------ the lock
    def _acquire(self, what: str, timeout_s: float = -1.0) -> bool:
        if self._lock.acquire(blocking=False):
            return True
        self.point(f"{what}: waiting for the lock")
        return self._lock.acquire(timeout=timeout_s)

    # ------------------------------------------------------------------ motion held
    def hold(self, reason: str) -> None:
        """No operation or command from here on, each refused with ``reason`` (what to do
        included), until :meth:`allow`; one under way ends at its next step (its generation is
        preempted); nothing is re-enabled after a reset. Sends nothing: the caller's stop does."""
        with self._lock:
            self.held = reason
            self.generation += 1
            self._preempted = (self.generation, reason)
            self.was_enabled = False  # a drive that resets meanwhile is not enabled again
        self._wake()

    def allow(self) -> None:
        """Motion taken again (each command still needs its enable: nothing is enabled here); the
        hold's reason is no longer why the drive stands ("not armed", not "inactive")."""
        with self._lock:
            if self._preempted[1] == self.held:
                self._preempted = (self._preempted[0], "")
            self.held = ""

    def admit(self, doing: str) -> None:
        """Refuse ``doing`` while motion is held: the one verdict every way to the drive asks."""
        reason = self.held
        if reason:
            raise CommandRejected(f"{self.name}: {doing} refused: {reason}. Nothing was sent.")

    # ------------------------------------------------------------------ operations and stops
    @contextmanager
    def operation(self, name: str, parent: Op | None = None, *, unless_stopped_since: int | None = None
                  ) -> Iterator[Op]:
        """An operation that waits for the drive: registered busy under its own token (refused
        while another runs), or run under ``parent``'s token and generation (a nested call).
        ``unless_stopped_since``: refused when a stop came after that :attr:`stop_mark`."""
        if parent is not None:
            self.check(parent, name)
            yield parent
            return
        self._acquire(name)
        try:
            self.admit(name)
            if unless_stopped_since is not None and self._preempted[0] != unless_stopped_since:
                raise DriveStateError(f"{self.name} (node {self.node_id}): {name} refused: stopped since it was asked"
                                      f" ({self._preempted[1]}); nothing was sent", node_id=self.node_id)
            if self._busy:
                raise CommandRejected(f"{self.name}: {name} refused: the drive is busy with {self.busy};"
                                      " nothing was sent. Try again when it is done.")
            self.generation += 1
            op = self._busy.add(name, self.generation)
        finally:
            self._lock.release()
        yield from self._run_registered(op)

    def _run_registered(self, op: Op) -> Iterator[Op]:
        try:
            yield op
        finally:
            with self._lock:
                self._busy.remove(op)

    def check(self, op: Op, doing: str) -> None:
        """Raise when a stop came since ``op`` began, or the driver shut down."""
        if self.closed:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing}: the driver shut down meanwhile",
                                  node_id=self.node_id)
        self.admit(doing)
        before, by = self._preempted
        if op.generation < before:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing} interrupted by {by}",
                                  node_id=self.node_id)

    @contextmanager
    def stopping(self, command: Command, by: str) -> Iterator[Op]:
        """A stop: its frame now (:meth:`stop`), then registered busy while the caller waits for
        the drive to get there (commands meanwhile are refused; another stop is not)."""
        self.stop(command, by)
        with self._lock:
            op = self._busy.add(by, self.generation)
        yield from self._run_registered(op)

    def stop(self, command: Command, by: str, timeout_s: float = -1.0) -> bool:
        """The frame of a stop: decided and sent in one critical section that bumps the
        generation, so no frame decided before it can follow it. Forgets the set-point handshake
        and the commanded state; wakes every operation waiting; False, nothing sent, without the lock in ``timeout_s``."""
        if not self._acquire(by, timeout_s):
            return False
        try:
            self.generation += 1
            self._preempted = (self.generation, by)
            self.was_enabled = False
            self.velocity_commanded = False
            self._handshake.reset()
            self.cw = int(command)
            self.point(f"{by}: decided")
            sdo_word = self._emit_cw(self.cw)
        finally:
            self._lock.release()
        if sdo_word is not None:
            self._write_cw_sdo(sdo_word)
        self._wake()
        return True

    def transition(self, op: Op, doing: str, command: Command | int, edge: int = 0) -> None:
        """One controlword of an operation (enable, recover, homing): sent only if no stop came
        since ``op`` began, checked under the lock with the frame."""
        self._acquire(doing)
        try:
            self.check(op, doing)
            self.point(f"{doing}: decided")
            self.cw = int(command)
            if self.cw & ENABLED_CW_MASK == ENABLED_CW_MASK:
                self.last_enable_sent = time.monotonic()
            sdo_word = self._emit_cw(self.cw | edge)
        finally:
            self._lock.release()
        if sdo_word is not None:
            self._write_cw_sdo(sdo_word)
            self._restop_after_sdo(op)

    def mark_enabled(self, op: Op, verdict: Callable[[], None]) -> None:
        """The end of an enable: ``verdict`` (raises when the drive is not enabled) and the mark,
        under the lock, after the check that no stop came."""
        with self._lock:
            self.check(op, "enable")
            verdict()
            self.was_enabled = True
            self.enables += 1

    def confirm_armed(self, since: int) -> bool:
        """An enable of a drive armed already (the caller read Operation Enabled from it after the
        stop mark ``since``): counted as an enable, as one that walked the states would be (the
        drive system takes a wheel back on it), unless a stop or a hold came since, an operation
        is under way or this driver's last word is no longer Enable Operation. Nothing is sent."""
        with self._lock:
            if (self.closed or self.held or self._busy.oldest or self._preempted[0] != since
                    or self.cw & ENABLED_CW_MASK != ENABLED_CW_MASK):
                return False
            self.was_enabled = True
            self.enables += 1
            return True

    def _restop_after_sdo(self, op: Op) -> None:
        """A controlword written by SDO after the lock: a stop decided meanwhile is written again."""
        with self._lock:
            word = self.cw if op.generation < self._preempted[0] and self.cw in STOP_WORDS else None
        if word is not None:
            self._write_cw_sdo(word)

    def _emit_cw(self, word: int) -> int | None:
        """Under the lock: the controlword on its RPDO; or, with no RPDO for it, the word to write
        by SDO once the lock is released."""
        pdo = self._plan.rpdo_with(OD.CONTROLWORD)
        if pdo is None:
            return word
        self._send(pdo.cob_id, encode_rpdo(pdo, {OD.CONTROLWORD: word, OD.TARGET_POSITION: self.target_counts,
                                                 OD.TARGET_VELOCITY: 0}))
        return None

    # ------------------------------------------------------------------ commands (one frame)
    def command(self, name: str, op: Op | None = None, *, stop: bool = False) -> LockedCommand:
        """``with command(name) as frames``, a command of a frame or two: the lock for at most
        COMMAND_LOCK_WAIT_S; refused at once while an operation other than ``op`` runs, while motion
        is held (unless it is a ``stop``: a halt), and, with ``op``, when a stop preempted it
        (LockedCommand, not a generator context manager: 1 us less a command)."""
        return LockedCommand(self, name, op, stop)

    def _enter_command(self, name: str, op: Op | None, stop: bool) -> None:
        if not self._acquire(name, COMMAND_LOCK_WAIT_S):
            raise CommandRejected(f"{self.name}: {name} refused: another command holds the drive; nothing was sent")
        try:
            if not stop:
                self.admit(name)
            if self._busy and (other := self._busy.other_than(op)):
                raise CommandRejected(f"{self.name}: {name} refused: the drive is busy with {other};"
                                      " nothing was sent. Send it again when that is done.")
            if op is not None:
                self.check(op, name)
        except BaseException:
            self._lock.release()
            raise

    def try_command(self, name: str) -> LockedCommand | None:
        """The supervisor's way in (never waits): the lock now, or None while any operation runs; then :meth:`release`."""
        if not self._lock.acquire(blocking=False):
            return None
        if self._busy:
            self._lock.release()
            return None
        return LockedCommand(self, name)

    def release(self) -> None:  # after try_command
        self._lock.release()

    # the senders below run under the lock (reached only through LockedCommand or the handshake)
    def _require_enabled_word(self, doing: str) -> None:
        if self.cw & ENABLED_CW_MASK != ENABLED_CW_MASK:
            raise CommandRejected(f"{self.name}: {doing} refused: a stop came first (controlword"
                                  f" 0x{self.cw:04X}); nothing was sent. enable() it again.")

    def _send_setpoint(self, counts: int) -> None:
        """A target with controlword bit 4 rising (the handshake's, under its lock and ours)."""
        self.target_counts = counts
        pdo = self._plan.rpdo_with(OD.TARGET_POSITION)
        cw = controlword(Command.ENABLE_OPERATION, new_setpoint=True, change_immediately=True) | (self.cw & CW.HALT)
        if pdo is not None:
            self._send(pdo.cob_id, encode_rpdo(pdo, {OD.CONTROLWORD: cw, OD.TARGET_POSITION: counts}))
        else:  # 0x607A only by SDO: written before (motion); here the edge alone
            self._send_rpdo_cw(cw)

    def _clear_setpoint(self) -> None:
        """Controlword bit 4 back to 0 after the acknowledge (the handshake's)."""
        self._send_rpdo_cw(int(Command.ENABLE_OPERATION) | (self.cw & CW.HALT))

    def _send_rpdo_cw(self, word: int) -> None:
        if self._emit_cw(word) is not None:  # motion refuses such a drive before any set-point
            raise CommandRejected(f"{self.name}: the controlword has no RPDO on this drive; nothing was sent")

    def on_status(self, acknowledged: bool) -> None:
        """Receive thread: a statusword came; the handshake's reply, if one is due. Takes the
        lock (held by nobody for longer than a frame), so its frame cannot follow a stop's."""
        if self._handshake.idle:
            return
        with self._lock:
            if self.cw & ENABLED_CW_MASK != ENABLED_CW_MASK:
                return  # a stop came first: it reset the handshake; nothing more goes out
            self._handshake.on_status(acknowledged)

    # ------------------------------------------------------------------ the driver's own resets
    def reset(self, position_counts: int) -> None:
        """Boot (the drive not booted): nothing commanded, the target where the shaft is."""
        with self._lock:
            self.cw = 0
            self.target_counts = position_counts
            self.was_enabled = False
            self.velocity_commanded = False
            self._handshake.reset()

    def forget(self, position_counts: int | None = None) -> None:
        """Before an enable or a mode switch: the handshake forgotten, the target where the shaft is."""
        with self._lock:
            self._handshake.reset()
            if position_counts is not None:
                self.target_counts = position_counts

    def forget_commanded(self, timeout_s: float = -1.0) -> bool:
        """A drive lost or another master's: nothing commanded any more (False: no lock in ``timeout_s``)."""
        if not self._lock.acquire(timeout=timeout_s):
            return False
        self.was_enabled = self.velocity_commanded = False  # nothing here raises: released below
        self._lock.release()
        return True

    def close(self) -> None:
        """The driver shuts down: every operation ends, no command is taken (stops still are)."""
        with self._lock:
            self.closed = True
        self._wake()


class StreamFrame(NamedTuple):
    """A streamed set-point's frame in one mode: its controlword, its target object and the RPDO
    that carries both (None: the target goes by SDO), with the order of the two in its payload
    (``cw_first``; None: that RPDO maps more, and the payload is :func:`encode_rpdo`'s)."""

    cw: int
    target: int
    pdo: PdoMap | None
    cw_first: bool | None

    @classmethod
    def of(cls, plan: PdoPlan, cw: int, target: int) -> StreamFrame:
        pdo = plan.rpdo_with(target)
        indexes = pdo.indexes if pdo is not None else ()
        pair = sorted(indexes) == sorted((_CONTROLWORD, target))
        return cls(cw, target, pdo, indexes[0] == _CONTROLWORD if pair else None)

    def payload(self, pdo: PdoMap, counts: int) -> bytes:
        """``pdo``'s (this frame's RPDO) bytes for a target of ``counts``: encode_rpdo's, packed without a
        mapping built for each set-point (tests/test_stream_frame.py holds the two equal)."""
        if self.cw_first is None:
            return encode_rpdo(pdo, {_CONTROLWORD: self.cw, self.target: counts})
        return pdo.codec.pack(self.cw, counts) if self.cw_first else pdo.codec.pack(counts, self.cw)


class LockedCommand:
    """One command holding the channel's lock (taken on enter, released on exit), handed out by
    :meth:`CommandChannel.command`: the frames it may send, each checking that this driver's last
    controlword was Enable Operation."""

    __slots__ = ("_c", "_doing", "_op", "_stop")

    def __init__(self, channel: CommandChannel, doing: str, op: Op | None = None, stop: bool = False) -> None:
        self._c, self._doing, self._op, self._stop = channel, doing, op, stop

    def __enter__(self) -> LockedCommand:
        self._c._enter_command(self._doing, self._op, self._stop)
        return self

    def __exit__(self, *exc: object) -> None:  # the lock taken in __enter__
        self._c._lock.release()

    @property
    def cw(self) -> int:
        return self._c.cw

    def velocity(self, counts_s: int, *, live: bool, stream: bool = False) -> None:
        """A velocity target on its RPDO (controlword Enable Operation beside it)."""
        self._target(OD.TARGET_VELOCITY, counts_s, live)
        if stream:
            self._c.stream_velocity_counts_s = counts_s

    def torque(self, permille: int, *, live: bool) -> None:
        self._target(OD.TARGET_TORQUE, permille, live)

    def _target(self, index: int, value: int, live: bool) -> None:
        c = self._c
        c._require_enabled_word(self._doing)
        pdo = c._plan.rpdo_with(index)
        if pdo is None:
            raise CommandRejected(f"{c.name}: {self._doing}: 0x{index:04X} has no RPDO here; nothing was sent")
        c._send(pdo.cob_id, encode_rpdo(pdo, {OD.CONTROLWORD: int(Command.ENABLE_OPERATION) | (c.cw & CW.HALT),
                                              index: value}))
        self.commanded(live)

    def commanded(self, live: bool) -> None:
        """A velocity or torque command went out (by RPDO, or by SDO before this): the watchdog's.
        One that goes live wakes the supervisor: its watchdog and limit guard look every period
        from now (a quiet supervisor waits longer: Supervisor.wait_s)."""
        c = self._c
        c.last_velocity_cmd = time.monotonic()
        went_live = live and not c.velocity_commanded
        c.velocity_commanded = live
        if went_live:
            c.on_live()

    def setpoint(self, counts: int) -> None:
        """A profile-position target through the set-point handshake (halt cleared)."""
        c = self._c
        c._require_enabled_word(self._doing)
        c.cw &= ~CW.HALT
        c._handshake.command(counts)

    def stream_position(self, mode: OperationMode, counts: int, sdo_written: bool) -> None:
        """A CSP or IP set-point: on its RPDO, or (``sdo_written``) its controlword alone."""
        c = self._c
        c._require_enabled_word(self._doing)
        c.target_counts = counts
        frame = c._streams[mode]  # IP: "enable ip mode", the drive follows 0x60C1:1 at each SYNC
        pdo = frame.pdo
        if pdo is not None and not sdo_written:
            c._send(pdo.cob_id, frame.payload(pdo, counts))
        else:
            c._send_rpdo_cw(frame.cw)

    def halt(self, on: bool) -> None:
        c = self._c
        c.cw = (c.cw | CW.HALT) if on else (c.cw & ~CW.HALT)
        word = c._emit_cw(c.cw)
        if word is not None:
            raise CommandRejected(f"{c.name}: halt: the controlword has no RPDO on this drive; nothing was sent")

    def brake(self, velocity_mode: bool) -> bool:
        """Zero velocity or zero torque, only while this driver's last word was Enable Operation
        (never after a stop: that frame would carry Enable Operation again). True when sent."""
        c = self._c
        c.velocity_commanded = False
        if c.cw & ENABLED_CW_MASK != ENABLED_CW_MASK:
            return False
        if velocity_mode:
            self.velocity(0, live=False)
        else:
            self.torque(0, live=False)
        return True
