"""The state cache: what the driver knows of one drive, fed by the bus's receive thread.

Owner: the bus's receive thread (``on_tpdo``, ``on_sync``, ``on_heartbeat``, ``on_emcy``), the only writer of
the received state (``_rx``): each TPDO's values are published as one immutable :class:`Received`
in a single assignment, so a reader never sees half a frame, stamped when it was measured (a
synchronous TPDO at its bus's SYNC before it: :meth:`DriveCache._measured_at`); the heard NMT state and heartbeat
time, EMCY, the guard toggle and the counters are its own too. It notifies waiters
(:meth:`wait_until`) and sends nothing: the set-point handshake's reply is the command channel's
(``StatusSink.on_status``).

Written through this object's methods by others, each on a field of its own (one writer each),
never on the receive thread's: what boot or a mode switch read by SDO (:meth:`seed`,
:meth:`note_statusword`, :meth:`note_mode`: the bus's worker or a command thread, one at a time
under the channel's busy registry) is a :class:`Noted` of its own, laid over the TPDOs' values
while it is the newer (:attr:`received`) and carried into the next TPDO's by the receive thread;
boot sets the scale, the guarding flag and its generation (the receive thread restarts its
toggle when the generation changes), and notes the NMT start (``_started_at``: the NMT state and
heartbeat time read it with the heard ones); a command thread acknowledges faults and EMCYs it
has dealt with (an acknowledgement is a sequence number, so a FAULT that arrives after it is
never erased by it).

An EMCY costs the receive thread little (a babbling node sends thousands a second): its log
lines are at most one every EMCY_LOG_PERIOD_S per drive, each with the count held back since
the last. The cause of a fault (the newest EMCY with an error code) is kept until this driver
resets the fault (:meth:`DriveCache.acknowledge_emcy`): an EMCY 0x0000 (error reset) that comes
while the drive still says FAULT, a spoofed one or one ahead of its statusword, clears nothing.

Lost, booted, another master: the supervisor's judgement (:class:`motor_driver.drive.ledger.DriveRecord`),
read here, never written: the receive thread posts each heartbeat that may change it
(:class:`motor_driver.drive.ledger.Heard`) and goes on.

The verdict's inputs, one writer each: the received state, the heard NMT state and heartbeat
time, the EMCY and the FAULT count are the receive thread's; ``_noted`` is the SDO readers'
(boot, a mode switch: one at a time under the channel's busy registry); ``_started_at``,
``_boot_fault_ack`` and ``_boot_trusts`` are boot's (the bus worker's); ``_fault_ack``,
``_emcy_ack`` and ``_cmd_trusts`` are the command threads' (enable, recover, homing: one at a time
under the busy registry). A request to take the next position as it comes is a count (boot's or a
command thread's): the receive thread sees it change and tells its position filter itself, so
the filter has one writer.

Truth paid once: :meth:`snapshot` reads the received state once, and the verdict and every value
published with it come from that one read. It is judged when one of its inputs changes, or a SYNC
period passed (the ages it carries are then at most one period old; the staleness bound is
judged exactly): otherwise every reader gets the same immutable :class:`DriveState`. The memo is
a cache of a pure function of those inputs, replaced whole in one assignment by whichever reader
judged first (two that race store equal values). The receive thread only decodes and stamps.
"""

from __future__ import annotations

import logging
import math
import struct
import threading
import time
from collections.abc import Callable

import canopen

from can_config.config import DriveConfig
from can_config.objects import EMCY_HEARTBEAT_LOST, OD, FunctionCode, NmtState, emcy_text
from motor_driver.drive.constants import TRANSITION_TIMEOUT_S
from motor_driver.drive.ledger import DriveRecord, Heard, SupervisorPort
from motor_driver.drive.received.position import PositionFilter
from motor_driver.drive.received.tpdo import decode_tpdo
from motor_driver.drive.values import DriveState, Emcy, Noted, Received, StatusSink
from motor_driver.drive.verdict import DriveFacts, Verdict, judge, missing_tpdos
from motor_driver.process.held import POLL_S, HeldDeadline, ReadBehind
from motor_driver.process.ratelimit import Throttle
from motor_driver.protocol.cia402 import FAULT_STATES, SW, State, decode_state
from motor_driver.protocol.pdo import TT_SYNC, PdoPlan, TpdoLayout
from motor_driver.protocol.units import Scale

logger = logging.getLogger(__name__)

_STATUSWORD = OD.STATUSWORD
#: What the verdict is judged from besides the cache's own (the host watch's and the command
#: channel's, handed by the facade): (another master's evidence, armed, stopped by, held, enables)
Others = tuple[str, bool, str, str, int]
NOBODY: Others = ("", False, "", "", 0)
_EMCY_HEAD = struct.Struct("<HB")
#: A drive's EMCY log lines: at most one every this long (the others counted, said with the next).
EMCY_LOG_PERIOD_S = 1.0
#: A synchronous TPDO not yet heard counts as having answered this many SYNCs before the first:
#: its first answer is taken for the newest SYNC's, never for a late one.
NEVER_ANSWERED = 10


#: One TPDO's decoding, read once a frame: (unpack, objects, sent every SYNC, carries the statusword)
Decoder = tuple[Callable[[bytes | bytearray], tuple[int, ...]], tuple[int, ...], bool, bool]


def _decoders(layouts: dict[int, TpdoLayout], per_sync: frozenset[int]) -> dict[int, Decoder]:
    return {cob: (lay.codec.unpack_from, lay.indexes, cob in per_sync, _STATUSWORD in lay.indexes)
            for cob, lay in layouts.items()}


class DriveCache:
    """Identity, the PDO layouts, and the received state of one drive."""

    #: the drive's units (the config's until a boot read the drive's own), and the quick-stop
    #: deceleration it was given (deg/s^2: the config's, or the drive's maximum where the config's is
    #: beyond its range): each the boot's to write; stops, guards and limits read them
    scale: Scale
    quick_stop_decel_deg_s2: float

    def __init__(self, config: DriveConfig, network: canopen.Network, plan: PdoPlan, scale: Scale, *,
                 sync_period_s: float, record: DriveRecord, port: SupervisorPort) -> None:
        self.config = config
        self._record, self._port = record, port  # the supervisor's record (read only) and port
        self.name, self.node_id = config.name, config.node_id
        self._network, self.sync_period_s = network, sync_period_s
        self._sink: StatusSink | None = None
        self._layouts = {p.cob_id: TpdoLayout.from_map(p) for p in plan.tpdos}
        self._has_torque = any(OD.TORQUE_ACTUAL in p.indexes for p in plan.tpdos)
        self._per_sync = frozenset(p.cob_id for p in plan.tpdos if p.trans_type == TT_SYNC)
        self._sync_heard = dict.fromkeys(sorted(self._per_sync), 0.0)  # each one's newest reception (monotonic)
        self.tpdos_per_sync, self._decoders = len(self._per_sync), _decoders(self._layouts, self._per_sync)
        self._event = threading.Condition()
        self._rx = Received()  # the receive thread's
        self._noted: Noted | None = None  # the SDO readers' (boot, a mode switch)
        self.scale, self.quick_stop_decel_deg_s2 = scale, config.quick_stop_decel_deg_s2
        self.positions = PositionFilter(config.node_id, sync_period_s)  # others read it; only this module calls it
        self.set_scale(scale)
        # receive thread
        self._fault_seq, self._fault_word = 0, 0  # FAULT statuswords seen, the last of them
        # positions taken; statuswords received (one that arrives after a frame was sent has a higher number)
        self.position_seq = self.status_seq = 0
        # TPDOs; EMCYs (logged or not); of them 0x8130 (no heartbeat heard from this host: what explains
        # the drive's own NMT change on that error, 0x1029; the supervisor reads it) and the newest one's arrival
        self.tpdo_count, self.emcy_count, self.host_loss_emcys, self.host_loss_at = 0, 0, 0, 0.0
        self.sync_tpdos = 0  # TPDOs received of those sent every SYNC (frame loss: expected per SYNC)
        # the bus stamps of the newest SYNC heard (when the next synchronous TPDOs measured) and of the one
        # before, the SYNCs heard, the count of the SYNC each synchronous TPDO answered last, and those whose
        self._sync_stamp, self._prev_sync_stamp, self._syncs, self._sync_answered, self._took_previous = (
            0.0, 0.0, 0, dict.fromkeys(self._per_sync, -NEVER_ANSWERED), set[int]())  # last answer was the one before's
        # the newest event-driven statusword's bus stamp; synchronous ones left as older (_keeps_newer_statusword)
        self._event_sw_stamp, self.stale_statuswords = 0.0, 0
        self.heartbeats = 0  # heartbeats (or guard answers) received
        self._sw_enabled = False
        self._behind_back: tuple[float, str] = (0.0, "")
        self._heard_nmt = self.reported_nmt = "UNKNOWN"
        self._bootup_at = self._operational_at = 0.0
        self.bootups = 0  # boot-ups heard: one numbered above what a configuration began with is a reset in it
        self._heard_at, self._heard_stamp = 0.0, 0.0  # the newest heartbeat: monotonic, and the bus's stamp of it
        self._last_emcy: Emcy | None = None
        self._emcy_log = Throttle(EMCY_LOG_PERIOD_S)  # the receive thread's (EMCY lines, wrong-length TPDOs)
        self.wrong_length_tpdos = 0  # TPDOs of a length this driver's mapping does not give (receive thread)
        self._guard_toggle = self._guard_seen = 0  # the toggle, and the guarding generation it belongs to
        self.guard_errors = self.guard_answers = 0  # guard answers refused, and taken (their toggle right)
        self._bootup = threading.Event()
        self._trusts_seen = (0, 0)  # the trust requests (boot's, the command threads') acted on
        # written by others through methods, one writer each
        self._fault_ack = self._boot_fault_ack = 0  # FAULTs dealt with: command threads' (enable, recover); boot's
        # take the next position as it comes: boot's count (its SDO seed), the command threads' (homing)
        self._boot_trusts = self._cmd_trusts = 0
        self._emcy_ack: Emcy | None = None  # command threads (recover)
        self.guarding = False  # boot
        self._guard_generation = 0  # boot: each set_guarding starts the toggle at 0
        self._started_at = 0.0  # boot: its NMT start (monotonic)
        self._on_sample: Callable[[], None] | None = None  # a trajectory group's (on_sample)
        self._stale_after_s, self._per_period = config.stale_after_syncs * sync_period_s, 1.0 / (sync_period_s or 1.0)
        # the judged snapshot (received, SYNC period, key, snapshot) and verdict (key, SYNC period,
        # verdict): any reader's, replaced whole (module docstring)
        self._judged: tuple[Received, int, tuple[object, ...], DriveState] | None = None
        self._verdict_memo: tuple[tuple[object, ...], int, Verdict] | None = None

    def on_sample(self, callback: Callable[[], None] | None) -> None:
        """``callback()`` on the receive thread after each new position sample (one per SYNC): a
        trajectory group's clock (motor_driver/follow/group.py). It must only wake a thread (set an
        event); None removes it."""
        self._on_sample = callback

    def connect(self, sink: StatusSink) -> None:
        """The channel that gets the statusword (before :meth:`subscribe`)."""
        self._sink = sink

    def subscribe(self) -> None:
        for cob in self._layouts:
            self._network.subscribe(cob, self.on_tpdo)
        if self._per_sync:
            self._network.subscribe(FunctionCode.SYNC, self.on_sync)
        self._network.subscribe(FunctionCode.HEARTBEAT + self.node_id, self.on_heartbeat)
        self._network.subscribe(FunctionCode.EMCY + self.node_id, self.on_emcy)

    # ------------------------------------------------------------------ what others read
    # (besides the plain attributes above: read by anyone, written only here, tests/test_ownership.py)
    @property
    def received(self) -> Received:
        """What the drive said last: the TPDOs' values, with what an SDO read noted since laid over them."""
        return self._noted.over(self._rx) if self._noted is not None else self._rx

    @property
    def nmt_state(self) -> str:
        """The NMT state heard last, or OPERATIONAL from boot's NMT start when that is newer."""
        return "OPERATIONAL" if self._started_at > self._heard_at else self._heard_nmt

    @property
    def last_heartbeat(self) -> float:
        """The newest heartbeat (monotonic; boot's NMT start counts as one); 0.0 never."""
        return max(self._heard_at, self._started_at)

    @property
    def heartbeat_stamp(self) -> float:
        """The bus's own stamp of the newest heartbeat (its clock, as
        :attr:`~motor_driver.bus.traffic.BusStats.read_to`); 0.0 when none, or when boot's NMT start
        is newer (no frame of the drive's)."""
        return self._heard_stamp if self._heard_at >= self._started_at else 0.0

    @property
    def state(self) -> State:
        return decode_state(self.received.statusword)

    def data_stale(self) -> bool:
        """No PDO for stale_after_syncs SYNC periods (what the snapshot calls stale). A drive sends
        PDOs only when OPERATIONAL: while they come, a PRE-OPERATIONAL or STOPPED heartbeat was
        sent before it obeyed an NMT start (on its way, or read late by a starved process)."""
        return self._stale(self._data_age(self.received, time.monotonic()))

    @staticmethod
    def _data_age(rx: Received, now: float) -> float:
        """Since the data was last whole (``Received.whole_rx``); inf: never."""
        return now - rx.whole_rx if rx.whole_rx else math.inf

    def _stale(self, data_age: float) -> bool:
        return data_age > self.config.stale_after_syncs * self.sync_period_s

    @property
    def angle_deg(self) -> float:
        return self.scale.counts_to_deg(self.received.position_counts)

    @property
    def fault_seen(self) -> int | None:
        """The last FAULT statusword seen since faults were acknowledged (by boot or a command), or None."""
        return self._fault_word if self._fault_seq > max(self._fault_ack, self._boot_fault_ack) else None

    @property
    def last_emcy(self) -> Emcy | None:
        emcy = self._last_emcy
        return None if emcy is self._emcy_ack else emcy

    def reset_since_operational(self) -> bool:
        """A boot-up came after the drive's last OPERATIONAL heartbeat."""
        return self._bootup_at > self._operational_at

    @property
    def behind_back(self) -> tuple[float, str]:
        return self._behind_back

    @property
    def booted(self) -> bool:
        return self._record.booted

    @property
    def lost(self) -> bool:
        return self._record.lost

    def expect_bootup(self) -> None:
        """Boot, before its NMT reset: the next boot-up is the one it waits for."""
        self._bootup.clear()

    def wait_bootup(self, timeout_s: float) -> bool:
        return self._bootup.wait(timeout_s)

    # ------------------------------------------------------------------ waiting
    def wait_until(self, done: Callable[[], bool], timeout_s: float, *, behind: ReadBehind | None = None) -> bool:
        """Wait for ``done()`` (checked at each statusword and stop); False at the timeout.
        ``done`` may raise to end the wait. After a hold of this process that left less than a
        look of the wait, it looks once more (:class:`HeldDeadline`): what the drive said while
        the process was held is read before the verdict. With ``behind`` (a wait for what the
        drive says: a state, a target reached, a new position), past the deadline it looks on
        while this driver's receive thread has yet to hand on what came (:class:`ReadBehind`,
        bounded; asked with the lock let go, so that a thread delivering meanwhile is not taken
        for behind); the caller's timeout says what it saw."""
        deadline = HeldDeadline(timeout_s)
        with self._event:
            while not done():
                remaining = deadline.remaining()
                if remaining <= 0:
                    if behind is None:
                        return False
                    self._event.release()
                    try:
                        again = behind.wait_on()
                    finally:
                        self._event.acquire()
                    if not again:  # caught up (or given up): what it handed on meanwhile decides
                        return bool(done())
                    remaining = POLL_S
                self._event.wait(min(remaining, POLL_S))
        return True

    def wake(self) -> None:
        with self._event:
            self._event.notify_all()

    # ------------------------------------------------------------------ others' writes, one each
    def set_scale(self, scale: Scale) -> None:
        """Boot: the drive's units (read from it) replace the config's."""
        self.scale = scale
        self.positions.set_units(scale, self.config.max_velocity_deg_s)

    def set_quick_stop_decel(self, deg_s2: float) -> None:
        """Boot: the deceleration the drive's quick stop brakes at, read back from it."""
        self.quick_stop_decel_deg_s2 = deg_s2

    def seed(self, statusword: int, position_counts: int, mode: int) -> None:
        """Boot (drive not booted, no PDO flows yet): the state read by SDO; the next position
        TPDO is trusted as it comes."""
        self._noted = Noted(time.monotonic(), statusword=statusword, position_counts=position_counts, mode=mode)
        self._boot_trusts += 1

    def note_mode(self, mode: int) -> None:
        """A mode switch confirmed by SDO (0x6061): the cache shows it before the next TPDO."""
        self._noted = Noted(time.monotonic(), mode=mode)

    def note_statusword(self, statusword: int) -> None:
        """Boot: a statusword read by SDO before PDOs flow."""
        self._noted = Noted(time.monotonic(), statusword=statusword)

    def trust_next_position(self) -> None:
        """Homing moved the zero: the next position is taken as it comes (by the receive thread)."""
        self._cmd_trusts += 1

    def acknowledge_faults(self) -> None:
        """enable()/recover(): faults seen until now are dealt with; a later one stops motion anew."""
        self._fault_ack = self._fault_seq

    def acknowledge_emcy(self) -> None:
        """recover(): the EMCY seen until now is dealt with (a newer one still shows)."""
        self._emcy_ack = self._last_emcy

    def set_guarding(self, on: bool) -> None:
        """Boot: the drive answers guards (its toggle starts at 0 after a reset)."""
        self.guarding = on
        self._guard_generation += 1

    def note_started(self) -> None:
        """Boot, at NMT start (the supervisor marks the drive booted when boot reports it)."""
        self._started_at = time.monotonic()
        self._boot_fault_ack = self._fault_seq

    # ------------------------------------------------------------------ the receive thread
    def on_sync(self, cob_id: int, data: bytearray, timestamp: float) -> None:
        """A SYNC on this drive's bus (its stamp: when it was on the bus): the moment the drive
        latches what its next synchronous TPDOs carry (CiA 402)."""
        self._prev_sync_stamp, self._sync_stamp = self._sync_stamp, timestamp
        self._syncs += 1

    def _measured_at(self, cob_id: int, timestamp: float) -> float:
        """When a TPDO received with the bus stamp ``timestamp`` measured what it carries: a
        synchronous one at the SYNC before it (CiA 402 drives latch their actual values at the
        SYNC; its answer comes within the SYNC period, CiA 301's synchronous window), any other when
        it was sent. A TPDO that answered every SYNC until the one before the newest and comes after
        the newest is the late answer to that one (latched there: stamped with it, never one period
        too new), unless its last frame was taken so too: two in a row are taken as a SYNC it did
        not answer (its answer lost, or never sent) and an answer to the newest, which it is stamped
        with (else one lost answer would stamp every later one a period early, for good).

        The counts cannot tell that from answers that keep coming after the next SYNC (a bus over
        its capacity, which the bus audit names): such a run is stamped a period too new from its
        second frame on, until an answer comes before the next SYNC. One back after a longer
        silence answers the newest. A frame more than a period after the newest SYNC (a SYNC not
        heard; a bus that does not show this driver its own SYNC: a kernel socket sending it) keeps
        its own stamp, and the SYNC it answered is counted all the same."""
        if cob_id not in self._per_sync:
            return timestamp
        behind = self._syncs - self._sync_answered[cob_id]
        if behind == 2 and cob_id not in self._took_previous:
            self._sync_answered[cob_id] = self._syncs - 1
            self._took_previous.add(cob_id)
            sync = self._prev_sync_stamp
        elif behind >= 1:
            self._sync_answered[cob_id] = self._syncs
            self._took_previous.discard(cob_id)
            sync = self._sync_stamp
        else:
            return timestamp
        return sync if 0.0 <= timestamp - self._sync_stamp < self.sync_period_s else timestamp

    def on_tpdo(self, cob_id: int, data: bytearray, timestamp: float) -> None:
        unpack, indexes, per_sync, has_statusword = self._decoders[cob_id]
        try:
            values = unpack(data)
        except struct.error:
            self._wrong_length(cob_id, data)
            return
        if per_sync:
            timestamp = self._measured_at(cob_id, timestamp)
        noted = self._noted
        rx = noted.over(self._rx) if noted is not None else self._rx  # self.received
        boot_trusts, cmd_trusts = self._boot_trusts, self._cmd_trusts
        if boot_trusts != self._trusts_seen[0] or cmd_trusts != self._trusts_seen[1]:  # asked by boot or homing
            self._trusts_seen = (boot_trusts, cmd_trusts)
            self.positions.trust_next()
        sw, mode, position, velocity, torque, took = decode_tpdo(indexes, values, rx, timestamp, self.positions)
        if has_statusword:
            if not per_sync:
                self._event_sw_stamp = timestamp
            elif (sent := self._event_sw_stamp) > timestamp and sent - timestamp < self.sync_period_s:
                sw, has_statusword = rx.statusword, False  # _keeps_newer_statusword
                self.stale_statuswords += 1
        now = time.monotonic()
        if took:
            self.position_seq += 1
            position_stamp, position_rx = timestamp, now
        else:
            position_stamp, position_rx = rx.position_stamp, rx.position_rx
        if per_sync:
            heard = self._sync_heard
            heard[cob_id] = now
            whole = min(heard.values())
        else:
            whole = rx.whole_rx if self._per_sync else now
        state = decode_state(sw) if has_statusword else None
        if state in FAULT_STATES:
            self._fault_word = sw
            self._fault_seq += 1
        self._rx = Received(sw, mode, position, velocity, torque, timestamp, now, self.positions.reference, rx.noted_at,
                            position_stamp, position_rx, whole)
        self.tpdo_count += 1
        if per_sync:
            self.sync_tpdos += 1
        if took and (tick := self._on_sample) is not None:
            tick()
        if state is not None:
            self.status_seq += 1
            self._on_statusword(sw, state, now)

    # _keeps_newer_statusword: a statusword latched at a SYNC, received after an event-driven one the
    # drive sent after that SYNC, is older than the one held: the drive's transmit buffers go out by
    # identifier (CAN arbitration), so its TPDO1 sent on a change passes its synchronous TPDO3 latched
    # before the change. Taking it would show the state before the change for a SYNC period (a fault
    # shown as Operation Enabled again, an old set-point acknowledge to the handshake). Only within a
    # period after the SYNC: a later event cannot have passed it (CiA 301's synchronous window), and a
    # bus clock stepped back never stops the synchronous statuswords for good. Without the SYNC heard
    # (a kernel socket sending this driver's own) a synchronous TPDO keeps its own stamp: taken.

    def _wrong_length(self, cob_id: int, data: bytearray) -> None:
        self.wrong_length_tpdos += 1
        if (passed := self._emcy_log.admit(("tpdo length", cob_id))) is not None:  # at most one line a period
            held = f" ({passed[0]} more not logged in the last {passed[1]:.1f} s)" if passed[0] else ""
            logger.warning("node %d: TPDO 0x%03X with %d bytes, expected %d; ignored: its PDO mapping is not the"
                           " one this driver wrote (reset, or another tool remapped it)%s",
                           self.node_id, cob_id, len(data), self._layouts[cob_id].codec.size, held)

    def _on_statusword(self, sw: int, state: State, now: float) -> None:
        now_enabled = state == State.OPERATION_ENABLED
        sink = self._sink
        if now_enabled and not self._sw_enabled and self._record.booted and sink is not None and \
                not sink.enabled_by_us(now, TRANSITION_TIMEOUT_S):
            self._behind_back = (now, f"node {self.node_id} became OPERATION_ENABLED, which this driver did not"
                                      " command")
            self._port.wake()  # another master's sign: judged at the supervisor's next period, now
        self._sw_enabled = now_enabled
        if sink is not None:
            try:  # the handshake's reply: the channel's, never the reason this thread dies
                sink.on_status(bool(sw & SW.SETPOINT_ACK))
            except Exception as err:
                logger.warning("node %d: set-point handshake: %s", self.node_id, err)
        with self._event:
            self._event.notify_all()

    def on_heartbeat(self, cob_id: int, data: bytearray, timestamp: float) -> None:
        if not data:
            return
        self.heartbeats += 1
        state = data[0] & 0x7F
        if self._guard_seen != self._guard_generation:  # boot restarted guarding: the toggle starts at 0
            self._guard_seen, self._guard_toggle = self._guard_generation, 0
        if self.guarding and state != NmtState.BOOTUP:  # a guard's answer: its toggle must alternate
            toggle = data[0] >> 7
            if toggle != self._guard_toggle:
                self.guard_errors += 1
                logger.warning("node %d (%s): node guarding answer with toggle %d, expected %d; not counted",
                               self.node_id, self.name, toggle, self._guard_toggle)
                self._guard_toggle = toggle ^ 1  # in step again from the next answer on
                return
            self._guard_toggle ^= 1
            self.guard_answers += 1
        self._heard_stamp = timestamp
        now = self._heard_at = time.monotonic()
        was = self.reported_nmt
        if state == NmtState.BOOTUP:
            self._heard_nmt = self.reported_nmt = "BOOTUP"
            self._bootup_at = now
            self.bootups += 1
            self._bootup.set()
            self._port.post(Heard(self.name, state, was, now, self.bootups))
            return
        try:
            heard = NmtState(state).name
        except ValueError:
            heard = f"0x{state:02X}"
        self._heard_nmt = self.reported_nmt = heard
        if state == NmtState.OPERATIONAL:
            self._operational_at = now
        # the supervisor judges a change (another master's, or its own NMT command's) and a lost drive heard again
        if heard != was or self._record.lost:
            self._port.post(Heard(self.name, state, was, now))

    def on_emcy(self, cob_id: int, data: bytearray, timestamp: float) -> None:
        if len(data) < 3:
            return
        code, register = _EMCY_HEAD.unpack_from(data)
        self.emcy_count += 1
        if code == EMCY_HEARTBEAT_LOST:
            self.host_loss_at = time.monotonic()
            self.host_loss_emcys += 1
        if code or decode_state(self.received.statusword) not in FAULT_STATES:  # a fault's cause stays
            self._last_emcy = Emcy(code, register, emcy_text(code), timestamp)
        passed = self._emcy_log.admit(None)
        if passed is None:
            return
        held = f" ({passed[0]} more EMCY from it in the last {passed[1]:.1f} s not logged)" if passed[0] else ""
        if code:
            logger.error("node %d (%s): EMCY 0x%04X %s (error register 0x%02X)%s", self.node_id,
                         self.name, code, emcy_text(code), register, held)
        else:
            logger.info("node %d (%s): EMCY error reset%s", self.node_id, self.name, held)

    # ------------------------------------------------------------------ the snapshot
    def _key(self, rx: Received, now: float, others: Others) -> tuple[object, ...]:
        """Every input of the verdict but the clock, and whether the data is past its bound: equal
        keys judge alike (ages aside)."""
        record, job = self._record, self._record.reboot_job
        late = not now - rx.whole_rx <= self._stale_after_s if rx.whole_rx else True
        return (rx.statusword, late, others, self._heard_at, self._started_at, self._last_emcy, self._emcy_ack,
                self._fault_seq, self._fault_ack, self._boot_fault_ack, record.lost, record.booted,
                record.reboot_wanted, job is not None and not job.done())

    def verdict(self, others: Others = NOBODY) -> Verdict:
        """The verdict alone (a command's check): judged again when an input changed; a verdict
        other than usable also once per SYNC period (its cause names an age)."""
        rx, now = self.received, time.monotonic()
        key, tick = self._key(rx, now, others), int(now * self._per_period)
        memo = self._verdict_memo
        if memo is not None and memo[0] == key and (memo[2].usable or memo[1] == tick):
            return memo[2]
        verdict = judge(self._facts(rx, now, others))
        self._verdict_memo = (key, tick, verdict)
        return verdict

    def snapshot(self, others: Others = NOBODY) -> DriveState:
        """What the driver knows of the drive, with the verdict on it, from one read of what it
        said: made again for a new frame, a changed input or a new SYNC period (module
        docstring). ``others``: the host watch's and the command channel's inputs (by default: no
        other master, not armed, no stop, nothing held, no enable)."""
        rx = self.received  # the one read: the verdict and the values below are of this frame
        now = time.monotonic()
        key, tick = self._key(rx, now, others), int(now * self._per_period)
        memo = self._judged
        if memo is not None and memo[0] is rx and memo[1] == tick and memo[2] == key:
            return memo[3]
        state = self._judge(rx, now, others)
        self._judged = (rx, tick, key, state)
        self._verdict_memo = (key, tick, state.verdict)
        return state

    def _facts(self, rx: Received, now: float, others: Others) -> DriveFacts:
        """What the verdict is judged from (:mod:`motor_driver.drive.verdict`), each input read once
        from its one writer, the received state given (the snapshot's one read)."""
        record = self._record
        emcy = self.last_emcy
        job = record.reboot_job
        rebooting = not record.booted and (record.reboot_wanted or self.reset_since_operational() or
                                            (job is not None and not job.done()))
        heard = self.last_heartbeat
        foreign_master, armed, stopped_by, held, enables = others
        return DriveFacts(self.name, data_age_s=self._data_age(rx, now), stale_after_s=self._stale_after_s,
                          heartbeat_age_s=now - heard if heard else math.inf, nmt=self.nmt_state,
                          state=decode_state(rx.statusword), lost=record.lost, booted=record.booted,
                          rebooting=rebooting, foreign_master=foreign_master, armed=armed, stopped_by=stopped_by,
                          held=held, enables=enables,
                          emcy_code=emcy.code if emcy is not None else 0, emcy_text=emcy.text if emcy is not None else "",
                          emcy_stamp=emcy.timestamp if emcy is not None else 0.0, fault_seen=self.fault_seen or 0,
                          missing=missing_tpdos(self._sync_heard, self._layouts, now=now, bound=self._stale_after_s))

    def _judge(self, rx: Received, now: float, others: Others) -> DriveState:
        facts = self._facts(rx, now, others)
        verdict = judge(facts)
        sw, state = rx.statusword, facts.state
        error_code = facts.emcy_code
        data_age = facts.data_age_s
        scale = self.scale
        torque = scale.permille_to_nm(rx.torque_permille) if self._has_torque else math.nan
        return DriveState.judged_as(
            facts, verdict,
            name=self.name, node_id=self.node_id, angle_deg=scale.counts_to_deg(rx.position_counts),
            velocity_deg_s=scale.counts_s_to_deg_s(rx.velocity_counts_s), torque_nm=torque,
            statusword=sw, state=state, mode=rx.mode, nmt=facts.nmt, error_code=error_code,
            error_text=facts.emcy_text if error_code else "",
            stamp=rx.stamp, heartbeat_age_s=facts.heartbeat_age_s,
            target_reached=bool(sw & SW.TARGET_REACHED), data_age_s=data_age,
            foreign_master=facts.foreign_master, reference=rx.reference, rx_monotonic=rx.rx_monotonic,
            position_stamp=rx.position_stamp, position_rx=rx.position_rx, whole_rx=rx.whole_rx)
