"""The CiA 402 power state machine of one drive: enable, the stops, recover, the mode switch.

Owner: command threads; the only state of its own is the supported-modes cache (0x6502, read
once per boot). Every controlword it sends goes through the command channel
(:mod:`motor_driver.drive.command.channel`), which owns the word, the busy registry and the
generation: an operation that waits here (enable, recover, a mode switch) is registered busy
and never holds a lock while it waits; a stop preempts it, and its frame is the last the drive
gets. Nested calls (homing's enable and mode switches) run under their caller's operation.
"""

from __future__ import annotations

import logging
import time

from canopen.objectdictionary import ObjectDictionary

from can_config.config import DriveConfig
from can_config.eds import has_object
from can_config.errors import CommandRejected, DriveStateError, DriveTimeoutError, MotorError
from can_config.objects import EMCY_HEARTBEAT_LOST, OD, SUPPORTED_MODE_BIT, OperationMode, emcy_text
from motor_driver.drive.command.busy import Op
from motor_driver.drive.command.channel import CommandChannel
from motor_driver.drive.constants import (
    ENABLE_STEPS,
    ENABLED_CW_MASK,
    FRESH_STATUS_MARGIN_S,
    FRESH_STATUS_SYNCS,
    MODE_SWITCH_TIMEOUT_S,
    STATE_POLL_S,
    TORQUE_MODES,
    TRANSITION_TIMEOUT_S,
    VELOCITY_MODES,
)
from motor_driver.drive.received.state import DriveCache, Others
from motor_driver.drive.sdo import SdoPort
from motor_driver.drive.setup.hostwatch import HostWatch
from motor_driver.drive.values import DriveState
from motor_driver.drive.verdict import UNREACHABLE, Condition, Verdict
from motor_driver.process.held import LATE_READER_HELPS, ReadBehind
from motor_driver.protocol.cia402 import FAULT_STATES, SW, Command, State, braked, decode_state, next_step_to_enable

logger = logging.getLogger(__name__)

#: How long past its timeout a stop's confirmation looks on while the receive thread is behind (s):
#: long enough for a kernel socket's thread to enter a marked wait (its first look always counts
#: as behind: motor_driver.bus.adapters.receive_behind) on a bus with SYNC, short beside the
#: 2 s an enable may look (the next drive's stop waits behind this one in safe_stop).
STOP_READ_BEHIND_S = 0.1
#: What a safe stop waits for a quick stop's ramp beyond twice its length from the drive's speed
#: (a statusword's way back, a drive that reports standstill late), s.
BRAKE_MARGIN_S = 0.5

#: The verdicts an operation that needs Operation Enabled goes on under (late: nothing says it
#: stopped), and those that mean the drive left Operation Enabled
_GOES_ON = frozenset({Condition.USABLE, Condition.LATE})
_LEFT_ENABLED = frozenset({Condition.STOPPED_ITSELF, Condition.FAULTED, Condition.NOT_ARMED})


class PowerStateMachine:
    """Enable, the stops, recover and the mode switch, through the command channel."""

    def __init__(self, config: DriveConfig, od: ObjectDictionary, cache: DriveCache, channel: CommandChannel,
                 sdo: SdoPort, watch: HostWatch) -> None:
        self.config, self._od, self._cache, self._channel, self._sdo = config, od, cache, channel, sdo
        self.name, self.node_id = config.name, config.node_id
        self._watch = watch
        self._supported_modes: int | None = None

    # ------------------------------------------------------------------ checks
    def others(self) -> Others:
        """What the verdict is judged from besides the cache's: the host watch's and the channel's."""
        channel = self._channel
        return (self._watch.foreign_master, channel.was_enabled, channel.stopped_by, channel.held, channel.enables)

    def verdict(self) -> Verdict:
        """The drive's verdict, read as a value (judged again only when an input changed)."""
        return self._cache.verdict(self.others())

    def snapshot(self) -> DriveState:
        """The drive's snapshot: its verdict and values from one read of what it said."""
        return self._cache.snapshot(self.others())

    def require_usable(self, doing: str, *, fresh: bool = False) -> Verdict:
        """Refuse ``doing`` (nothing sent) unless the drive can hear and answer this driver: the
        driver not shut down, and its verdict not another master, lost, re-booting or not
        configured; with ``fresh`` (a set-point: it acts on the state as read), not late either.
        Returns the verdict it judged by."""
        if self._channel.closed:
            raise DriveStateError(f"{self.name} (node {self.node_id}): {doing}: the driver is shut down;"
                                  " nothing was sent", node_id=self.node_id)
        verdict = self.verdict()
        condition = verdict.condition
        if condition is not Condition.USABLE and (condition in UNREACHABLE or (fresh and condition is Condition.LATE)):
            raise DriveStateError(f"{verdict.text()} ({doing} refused; nothing was sent)", node_id=self.node_id)
        return verdict

    def fault_error(self, doing: str) -> DriveStateError:
        emcy = self._cache.last_emcy
        code = emcy.code if emcy is not None else None
        what = f"EMCY 0x{code:04X} {emcy_text(code)}" if code else "no EMCY received"
        return DriveStateError(f"{self.name} (node {self.node_id}): {doing}: the drive is in FAULT"
                               f" ({what}); call recover() to reset it", node_id=self.node_id,
                               statusword=self._cache.received.statusword, error_code=code)

    def stopped_itself(self, doing: str) -> DriveStateError | None:
        """The error for an operation that needs Operation Enabled (homing, a move) when the drive
        left it on its own, read from its verdict: anything but usable ends the operation now, with
        the verdict's cause, rather than at its timeout; late data alone does not (nothing says it
        stopped: the operation's own timeout bounds it). A stop of this driver's own is the
        command channel's to say (checked first by the callers)."""
        verdict = self.verdict()
        if verdict.condition in _GOES_ON:
            return None
        why = f"the drive left Operation Enabled by itself ({verdict.cause})" \
            if verdict.condition in _LEFT_ENABLED else verdict.cause
        helps = f" ({verdict.helps})" if verdict.helps and verdict.condition in UNREACHABLE else ""
        emcy = self._cache.last_emcy
        hint = " (0x8130: it heard no heartbeat from this host: was this process stalled?)" \
            if emcy is not None and emcy.code == EMCY_HEARTBEAT_LOST else ""
        return DriveStateError(f"{self.name} (node {self.node_id}): {doing} ended: {why}{helps}{hint}; enable it"
                               " again to retry", node_id=self.node_id, statusword=self._cache.received.statusword,
                               error_code=emcy.code if emcy is not None else None)

    def read_behind(self, bound_s: float | None = None) -> ReadBehind:
        """A wait's look past its deadline while this drive's bus's receive thread is behind
        (:meth:`DriveCache.wait_until`), for at most ``bound_s`` (default READ_BEHIND_MAX_S): one per wait."""
        return ReadBehind(self._sdo.receive_behind, bound_s)

    def timed_out(self, behind: ReadBehind, read: tuple[str, str], drive: tuple[str, str],
                  statusword: int | None = None) -> DriveTimeoutError:
        """The error of a wait for what the drive says of itself that timed out, blaming the one
        that was late. Its receive thread still behind at the bound (``behind.gave_up``): what the
        drive said may be among what was not read, so the driver is named, in ``read``'s words;
        else the drive, in ``drive``'s. Each is (what, then): the look's words go between them."""
        if behind.gave_up:
            (what, then), looked = read, f"{behind.said()}. This driver was late, not the drive: {LATE_READER_HELPS}"
        else:
            (what, then), looked = drive, behind.said()
        return DriveTimeoutError(f"{what}{looked}{then}", node_id=self.node_id,
                                 statusword=self._cache.received.statusword if statusword is None else statusword)

    def wait_state(self, wanted: set[State], timeout_s: float, doing: str, *, fault_ok: bool = False,
                   op: Op | None = None, left: State | None = None, after: int | None = None,
                   look_on_s: float | None = None) -> State:
        """Wait for one of ``wanted``; a stop since ``op`` began ends the wait with its error.
        ``left``: also return when the drive shows another state than this one (the caller
        plans again from there). ``after``: only a statusword numbered above this counts (one
        that left the drive after a frame of ours), or, for a drive that reports its statusword
        only on change, the last one once FRESH_STATUS_SYNCS SYNC periods passed. ``look_on_s``:
        how long past the timeout it looks on while the receive thread is behind (read_behind)."""
        cache = self._cache
        fresh_by = time.monotonic() + FRESH_STATUS_SYNCS * cache.sync_period_s + FRESH_STATUS_MARGIN_S

        def done() -> bool:
            if op is not None:  # before the wanted state: a stop that landed meanwhile wins
                self._channel.check(op, doing)
            if after is not None and cache.status_seq <= after and time.monotonic() < fresh_by:
                return False
            state = cache.state
            if state in FAULT_STATES and not fault_ok and state not in wanted:
                raise self.fault_error(doing)
            return state in wanted or (left is not None and state != left)

        behind = self.read_behind(look_on_s)
        if cache.wait_until(done, timeout_s, behind=behind):
            return cache.state
        state, sw = cache.state, cache.received.statusword
        hint = ""
        if state == State.READY_TO_SWITCH_ON and not sw & SW.VOLTAGE_ENABLED:
            hint = " The drive reports no voltage: is STO low or the E-stop pressed?"
        who = f"{self.name} (node {self.node_id}): {doing}"
        word = f"{state.name} (statusword 0x{sw:04X}) after {timeout_s:g} s"
        raise self.timed_out(behind, (f"{who}: last read {word}", "."), (f"{who}: still in {word}", f".{hint}"), sw)

    # ------------------------------------------------------------------ enable
    def enable(self, timeout_s: float = TRANSITION_TIMEOUT_S, parent: Op | None = None, *,
               unless_stopped_since: int | None = None) -> None:
        """Walk the state machine to Operation Enabled (transitions 2, 3, 4), holding position.

        Refused for a drive that cannot watch the host (no 0x1016), unless the config allows it.
        A stop (quick stop, disable, the driver's close) preempts it; under ``parent`` (homing)
        a stop that preempted the caller preempts this too. ``unless_stopped_since``: a stop mark
        (:attr:`CommandChannel.stop_mark`); a stop since then refuses it (decided with its
        registration, so none can fall in between).
        """
        if parent is None and unless_stopped_since is None:
            # a stop from here on wins over this enable, as one after its registration does
            unless_stopped_since = self._channel.stop_mark
            if self._armed_already(unless_stopped_since):
                logger.debug("%s (node %d): armed already (Operation Enabled, read by SDO now)", self.name, self.node_id)
                return
        with self._channel.operation("enable", parent, unless_stopped_since=unless_stopped_since) as op:
            self.require_usable("enable")
            if self._watch.host_watch is None and not self.config.allow_no_host_watch:
                raise CommandRejected(f"{self.name} (node {self.node_id}): enable refused: {self._watch.host_watch_problem},"
                                      " so it would keep moving if this process were killed, hung or lost power."
                                      " Give it a heartbeat consumer, or set allow_no_host_watch: true for this"
                                      " drive (bench: --allow-no-host-watch) to arm it anyway. Nothing was sent.")
            self._wait_watching(op, timeout_s)
            self._cache.acknowledge_faults()  # asked again: from here on a FAULT stops motion anew
            self._channel.forget(self._cache.received.position_counts)
            # the drive's state now, by SDO (answered after this request): the cache may still show
            # Operation Enabled from before a stall in which the drive stopped itself (its host
            # watch), and an enable judged by that returned "armed" for a disabled drive
            now = decode_state(self._sdo.read_number(OD.STATUSWORD))
            if now != State.OPERATION_ENABLED:
                self._clear_held_target()
            self._walk_to_enabled(op, timeout_s, now)

            def verdict() -> None:
                if self._cache.state != State.OPERATION_ENABLED:
                    raise DriveTimeoutError(f"{self.name}: could not reach OPERATION_ENABLED", node_id=self.node_id,
                                            statusword=self._cache.received.statusword)

            self._channel.mark_enabled(op, verdict)  # the verdict and a stop are ordered too
        if parent is None:
            logger.info("%s (node %d): armed (Operation Enabled)", self.name, self.node_id)

    def _armed_already(self, since: int) -> bool:
        """Armed by this driver (its last controlword Enable Operation, no operation under way, the
        verdict usable) and the drive says Operation Enabled now (by SDO: answered after this
        request, not a statusword from before a stall). An enable then sends nothing and registers
        no operation: what streams to the drive is not refused meanwhile (a second /arm while a
        trajectory ran aborted the goal, "busy with enable"); it is counted as an enable. Anything
        else takes the whole path."""
        channel = self._channel
        channel.point("enable: armed already?")
        if channel.busy or channel.cw & ENABLED_CW_MASK != ENABLED_CW_MASK or not self.verdict().usable:
            return False
        try:
            if decode_state(self._sdo.read_number(OD.STATUSWORD)) != State.OPERATION_ENABLED:
                return False
        except MotorError:  # the whole path says what is wrong
            return False
        return channel.confirm_armed(since)  # counted, unless a stop came meanwhile

    def _wait_watching(self, op: Op, timeout_s: float) -> None:
        """Enable only a drive that is watching the host (its first host heartbeat or guard after
        its boot told it to): one enabled before would keep moving if this process died then."""
        if self._watch.host_watch is None:
            return
        self._channel.point("enable: host watch")

        def watching() -> bool:
            self._channel.check(op, "enable")
            return not self._watch.not_watching_yet()

        bound = max(timeout_s, self._watch.start_bound_s())
        if not self._cache.wait_until(watching, bound):
            raise DriveTimeoutError(f"{self.name} (node {self.node_id}): enable refused: the drive is not watching"
                                    f" the host after {bound:g} s: {self._watch.not_watching_yet()}. Enabled now, it"
                                    " would keep moving if this process died. Nothing was sent; enable it again.",
                                    node_id=self.node_id)

    def _walk_to_enabled(self, op: Op, timeout_s: float, first: State) -> None:
        """One transition at a time, each planned from the state the drive shows (the first from
        ``first``, read by SDO); a drive that shows another state than the one a step was planned
        from (a statusword that was on its way, a stop of another's) is planned for again from there."""
        for step_number in range(ENABLE_STEPS):
            state = first if step_number == 0 else self._cache.state
            if state == State.OPERATION_ENABLED:
                if self._channel.cw & ENABLED_CW_MASK != ENABLED_CW_MASK:  # enabled, but not by this driver's word
                    self._channel.transition(op, "enable", Command.ENABLE_OPERATION)
                return
            if state in FAULT_STATES:
                raise self.fault_error("enable")
            step = next_step_to_enable(state)
            if step is None:
                self.wait_state({State.SWITCH_ON_DISABLED, State.READY_TO_SWITCH_ON, State.SWITCHED_ON,
                                 State.OPERATION_ENABLED}, timeout_s, "enable", op=op)
                continue
            target, number, command = step
            logger.debug("node %d: transition %d to %s", self.node_id, number, target.name)
            self._channel.point(f"enable: before transition {number}")
            seq = self._cache.status_seq
            self._channel.transition(op, f"enable (transition {number} to {target.name})", command)
            self._channel.point(f"enable: sent transition {number}")
            self.wait_state({target, State.OPERATION_ENABLED}, timeout_s,
                            f"enable (transition {number} to {target.name})", op=op, left=state, after=seq)
        raise DriveTimeoutError(f"{self.name} (node {self.node_id}): enable: not OPERATION_ENABLED after"
                                f" {ENABLE_STEPS} transitions (now {self._cache.state.name}); is another master"
                                " commanding it?", node_id=self.node_id, statusword=self._cache.received.statusword)

    def _clear_held_target(self) -> None:
        """Before enabling: the drive still holds the last target from before a fault or a stop
        and follows it the moment it reaches Operation Enabled. Velocity and torque modes: a
        recovered wheel ran at its old 0x60FF (286 deg/s) until the watchdog; so 0 here. The
        cyclic position modes: a wheel stopped at speed brakes on past its last set-point
        (0x607A / 0x60C1:1) and jumped back to it (9 deg); so where the shaft is now (0x6064,
        read now: the braked shaft does not move). By SDO: the RPDO that carries the target
        also carries the controlword "enable operation"."""
        mode = self._cache.received.mode
        if mode in VELOCITY_MODES:
            self._sdo.write_typed(OD.TARGET_VELOCITY, 0, 0)
        elif mode in TORQUE_MODES:
            self._sdo.write_typed(OD.TARGET_TORQUE, 0, 0)
        elif mode in (OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION):
            actual = self._sdo.read_int(OD.POSITION_ACTUAL, 0)
            if actual is None:
                raise CommandRejected(f"{self.name} (node {self.node_id}): enable refused in"
                                      f" {OperationMode(mode).name}: the drive's EDS has no 0x6064, so its held"
                                      " set-point cannot be moved to where the shaft is. Nothing was sent.")
            self._channel.forget(actual)
            index, sub = (OD.TARGET_POSITION, 0) if mode == OperationMode.CYCLIC_SYNC_POSITION else \
                (OD.INTERPOLATION_DATA, 1)
            if has_object(self._od, index, sub):  # without it, nothing is held
                self._sdo.write_typed(index, sub, actual)

    # ------------------------------------------------------------------ the stops
    def _stop(self, name: str, command: Command, wanted: set[State], timeout_s: float) -> None:
        """A stop: its frame first, in the channel's critical section (it preempts every
        operation under way); then the wait for ``wanted`` (or a fault), no lock held."""
        seq = self._cache.status_seq
        with self._channel.stopping(command, name):
            self._channel.point(f"{name}: sent")
            # a short look past the timeout: a stop's confirmation holds up the next drive's stop
            # (safe_stop, the drive system's stopper); a reader behind longer is named, not waited for
            self.wait_state(wanted | FAULT_STATES, timeout_s, name, after=seq, look_on_s=STOP_READ_BEHIND_S)

    def disable(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        """Shutdown (transition 8 or 6): power stage off, drive in Ready to Switch On. A drive
        that says Switch On Disabled (or has not said it is ready) is sent Disable Voltage instead:
        Shutdown there is transition 2, a step toward enabled; Disable Voltage ends in Switch On
        Disabled from any state, so a state read late never costs the stop."""
        command = Command.DISABLE_VOLTAGE if self._cache.state in (
            State.SWITCH_ON_DISABLED, State.NOT_READY_TO_SWITCH_ON) else Command.SHUTDOWN
        self._stop("disable", command, {State.READY_TO_SWITCH_ON, State.SWITCH_ON_DISABLED}, timeout_s)

    def quick_stop(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        """Quick stop (transition 11; 7 or 10 from the states before): the drive brakes on its
        quick-stop ramp."""
        self._stop("quick stop", Command.QUICK_STOP, {State.QUICK_STOP_ACTIVE, State.SWITCH_ON_DISABLED}, timeout_s)

    def wait_braked(self, deadline: float) -> bool:
        """After a quick stop: until the drive has stopped braking (:func:`~motor_driver.protocol.
        cia402.braked`) or is lost, for at most :meth:`brake_bound_s` from its speed now, and never
        past ``deadline`` (monotonic: the safe stop's, for every drive at once). False: still
        braking when the wait ended."""
        cache = self._cache
        bound = min(self.brake_bound_s(cache.scale.counts_s_to_deg_s(cache.received.velocity_counts_s)),
                    deadline - time.monotonic())

        def done() -> bool:
            rx = cache.received
            return cache.lost or braked(cache.state, rx.statusword,
                                        cache.scale.counts_s_to_deg_s(rx.velocity_counts_s))
        return cache.wait_until(done, max(bound, 0.0))

    def brake_bound_s(self, velocity_deg_s: float, decel_deg_s2: float | None = None) -> float:
        """How long a quick stop from ``velocity_deg_s`` may take to brake: twice its ramp at
        ``decel_deg_s2`` (default: what the drive's quick stop brakes at, as its boot read it back),
        the speed counted at most twice the joint's limit (a garbage velocity waits no longer), and
        BRAKE_MARGIN_S."""
        speed = min(abs(velocity_deg_s), 2 * self.config.max_velocity_deg_s)
        return 2.0 * speed / (decel_deg_s2 or self._cache.quick_stop_decel_deg_s2) + BRAKE_MARGIN_S

    def disable_voltage(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        """Disable voltage (transitions 7, 9, 10, 12): power stage off, Switch On Disabled."""
        self._stop("disable voltage", Command.DISABLE_VOLTAGE, {State.SWITCH_ON_DISABLED}, timeout_s)

    def halt(self, on: bool) -> None:
        """Set or clear the halt bit (8): stop on the profile deceleration, stay enabled."""
        with self._channel.command("halt", stop=on) as frames:  # a halt is a stop; its release is not
            self.require_usable("halt")
            frames.halt(on)

    def recover(self, timeout_s: float = TRANSITION_TIMEOUT_S) -> None:
        """Fault reset (transition 15), then back to the enable state the drive had before."""
        with self._channel.operation("recover") as op:
            self.require_usable("recover")
            restore = self._channel.was_enabled
            cache = self._cache
            if cache.state in FAULT_STATES:
                if cache.state == State.FAULT_REACTION_ACTIVE:
                    self.wait_state({State.FAULT}, timeout_s, "recover (fault reaction)", fault_ok=True, op=op)
                self._channel.transition(op, "recover", 0)
                self._channel.transition(op, "recover", Command.FAULT_RESET)
                self.wait_state({State.SWITCH_ON_DISABLED}, timeout_s, "fault reset (transition 15)",
                                fault_ok=True, op=op)
                self._channel.transition(op, "recover", 0)
            cache.acknowledge_emcy()
            cache.acknowledge_faults()
            if restore:
                self.enable(timeout_s, parent=op)

    # ------------------------------------------------------------------ modes
    def supported_modes(self) -> int:
        """0x6502 as the drive reports it (read by SDO once per boot; all modes without it)."""
        if self._supported_modes is None:
            self._supported_modes = self._sdo.read_number(OD.SUPPORTED_DRIVE_MODES) \
                if has_object(self._od, OD.SUPPORTED_DRIVE_MODES) else 0xFFFF_FFFF
        return self._supported_modes

    def forget_modes(self) -> None:
        """Boot: a replaced drive may support other modes."""
        self._supported_modes = None

    def switch_mode_sdo(self, mode: OperationMode, op: Op | None = None) -> None:
        """0x6060 by SDO, then 0x6061 polled until it shows ``mode``. No lock is held: the caller
        registered an operation (``op``; none at boot); a stop meanwhile preempts it."""
        if op is not None:
            self._channel.check(op, f"mode switch to {mode.name}")
            self._channel.forget(self._cache.received.position_counts)
        self._sdo.write_typed(OD.MODES_OF_OPERATION, 0, int(mode))
        self._channel.point("mode switch: 0x6060 written")
        deadline = time.monotonic() + MODE_SWITCH_TIMEOUT_S
        while True:
            shown = self._sdo.read_number(OD.MODES_OF_OPERATION_DISPLAY)
            if op is not None:
                self._channel.check(op, f"mode switch to {mode.name}")
            if shown == mode:
                self._cache.note_mode(shown)
                return
            if time.monotonic() > deadline:
                raise DriveTimeoutError(f"node {self.node_id}: mode {mode.name} written to 0x6060 but"
                                        f" 0x6061 still shows {shown} after {MODE_SWITCH_TIMEOUT_S:g} s",
                                        node_id=self.node_id, statusword=self._cache.received.statusword)
            time.sleep(STATE_POLL_S)

    def set_mode(self, mode: OperationMode | int, parent: Op | None = None) -> None:
        """Switch the mode of operation; refuses modes 0x6502 does not list; waits for 0x6061.
        The drive is busy meanwhile (commands refused at once, a stop preempts it)."""
        self._channel.admit("mode switch")  # refused while held even when the drive is in ``mode`` already
        self.require_usable("mode switch")  # not to a drive lost, re-booting, unconfigured or another's
        mode = OperationMode(mode)
        bit = SUPPORTED_MODE_BIT.get(mode)
        supported = self.supported_modes()
        if bit is None or not supported >> bit & 1:
            raise CommandRejected(f"{self.name}: mode {mode.name} is not supported by node"
                                  f" {self.node_id} (0x6502 = 0x{supported:08X}); supported:"
                                  f" {', '.join(m.name for m, b in SUPPORTED_MODE_BIT.items() if supported >> b & 1)}")
        if self._cache.received.mode == mode:
            return
        with self._channel.operation("mode switch", parent) as op:
            self.switch_mode_sdo(mode, op)
