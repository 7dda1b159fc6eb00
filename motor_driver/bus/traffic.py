"""What the driver learns from the bus's traffic: counters and errors (:class:`BusStats`) and
evidence of another master (:class:`ForeignTraffic`), from its own listener.

Owner: the bus's receive thread writes both (each field in one assignment or under the
object's own short lock); the supervisor reads them.
"""

from __future__ import annotations

import logging
import time
from collections import deque
from collections.abc import Callable, Collection

import can

from can_config.bits import frame_bits
from can_config.errors import ForeignMasterError
from can_config.objects import FunctionCode
from motor_driver.protocol.errorframes import ErrorFrame, decode_error_frame

logger = logging.getLogger(__name__)

#: Another master's frames mark its drives for this long; the mark clears after this much quiet.
FOREIGN_HOLD_S = 0.5
#: Window in which SYNC frames are counted when the bus daemon sends the driver's own.
SYNC_RATE_WINDOW_S = 0.3
#: ... and the longer one that must agree: the driver's own SYNCs delivered in a bunch after a stall
#: (their receive timestamps crowd together; seen on the emulated SJA1000 pair: 11 in 0.3 s at a
#: 50 ms period) crowd the short window, but over this one they are no more than were sent; a
#: second master adds its whole rate to both (seen within about 0.7 s at the same period).
SYNC_RATE_LONG_WINDOW_S = 3.0
#: over the long window, this many times the driver's own count (plus two) is another master's
SYNC_RATE_LONG_FACTOR = 1.2
FOREIGN_RELEASE_S = 2.0
#: Before its first NMT command the driver (and each bench command) listens this long, at least,
#: for another master: two periods of the host heartbeat, if longer (:func:`look_for_master`).
LOOK_MIN_S = 0.2
#: A bench command, which may reset drives, listens this long by default: the longest host
#: heartbeat or SYNC period a config allows (1000 ms, can_config.model) and a tenth, so another
#: master within those bounds is heard at least once (LOOK_MIN_S missed a 1 s master half the time).
LOOK_BENCH_S = 1.1
#: A receive that failed is tried again after this pause (python-can's notifier loops on).
RX_ERROR_PAUSE_S = 0.05


class BusStats(can.Listener):
    """Frames received on a bus, error frames, and the load they make (worst-case bits)."""

    def __init__(self, bitrate: int) -> None:
        self.bitrate = bitrate
        self.frames = 0
        self.syncs = 0  # SYNC frames seen (this driver's own where the bus echoes them: a daemon's timer)
        self.error_frames = 0
        #: the newest error frame: (monotonic time, decoded); and the newest that loses the bus
        #: (bus-off, no ACK). Written by the receive thread (one assignment each), read by the
        #: supervisor, which reports and acts.
        self.last_error: tuple[float, ErrorFrame] | None = None
        self.last_losing_error = 0.0
        self.receive_error: tuple[float, str] | None = None
        #: the bus's own stamp (its clock: the kernel's, the daemon's) of the newest frame this
        #: thread has taken: how far it has read. Frames come in order, so a drive's heartbeat
        #: stamped before it was read (motor_driver.runtime.supervisor: a drive is silent by the
        #: bus's record, not by a starved reader's).
        self.read_to = 0.0
        #: when (monotonic) this thread last found its socket empty: the start of a wait that came
        #: back with nothing (not its end: a hold after it proves nothing of what came meanwhile),
        #: so every frame that had come by then was dispatched. The evidence of a
        #: silent bus, where no frame moves ``read_to``.
        self.idle_at = 0.0
        self.bits = 0
        self._window_start = time.monotonic()
        self._window_bits = 0
        self.load = 0.0

    def on_message_received(self, msg: can.Message) -> None:
        if msg.is_error_frame:
            self.read_to = msg.timestamp
            self.on_error_frame(msg.arbitration_id, msg.data)
            return
        syncs = 1 if msg.arbitration_id == 0x080 and not msg.is_extended_id else 0
        self.count(1, syncs, frame_bits(min(msg.dlc, 8), extended=msg.is_extended_id), msg.timestamp)

    def count(self, frames: int, syncs: int, bits: int, read_to: float) -> None:
        """Frames received (of them SYNCs) and their bits: one frame's, or a batch read's at once
        (motor_driver.bus.handle.FrameDispatch.on_frames); ``read_to``: the bus's stamp of the last."""
        self.read_to = read_to
        self.frames += frames
        self.syncs += syncs
        self.bits += bits
        self._window_bits += bits

    def on_idle(self, began: float) -> None:
        """The receive thread's wait that began at ``began`` (monotonic) came back with nothing: every
        frame that had come by then was taken (:attr:`idle_at`)."""
        self.idle_at = began

    def on_error_frame(self, can_id: int, data: bytes | bytearray) -> None:
        """An error frame (its class bits in ``can_id``): noted for the supervisor, which reports and acts."""
        self.error_frames += 1
        error = decode_error_frame(can_id, bytes(data))
        now = time.monotonic()
        self.last_error = (now, error)
        if error.loses_the_bus:
            self.last_losing_error = now

    def on_error(self, exc: Exception) -> None:
        """The receive thread's error (python-can calls it; handled here, the thread does not die
        with a traceback): noted for the supervisor, which declares the bus lost (the notifier's
        ``exception``) and reconnects. A kernel socket reports ENETDOWN once when its interface
        goes down and receives again when it is up; the pause bounds a receive that keeps failing
        to RX_ERROR_PAUSE_S per try (no spinning thread)."""
        self.receive_error = (time.monotonic(), str(exc))
        logger.debug("receive error: %s", exc)
        time.sleep(RX_ERROR_PAUSE_S)

    def sample(self) -> float:
        """Bus load (0..1) seen since the last sample."""
        now = time.monotonic()
        elapsed = now - self._window_start
        if elapsed > 0:
            self.load = self._window_bits / (elapsed * self.bitrate)
        self._window_start, self._window_bits = now, 0
        return self.load


class ForeignTraffic(can.Listener):
    """Frames that only another master sends (this driver never receives its own): SYNC, NMT
    commands, heartbeats with the host's own node id, SDO writes to this driver's drives.
    The receive thread stores when it last saw each (one assignment each); the supervisor
    reads them and decides."""

    def __init__(self, host_node_id: int, node_ids: Collection[int]) -> None:
        self.host_node_id = host_node_id
        self.node_ids = frozenset(node_ids)
        self.sync = 0.0
        #: set while this driver's SYNC reaches this listener (the socketcand daemon's timer, or the
        #: kernel's broadcast manager, whose frames SocketCAN loops back to the host's other
        #: sockets): another master's SYNC then shows as more SYNC frames than that period gives
        self.own_sync_period_s = 0.0
        #: SocketCAN marks each frame made on this host (is_rx False): a SYNC with is_rx True
        #: came over the wire from another node, which only another master sends
        self.marks_local_frames = False
        self._syncs: deque[float] = deque()  # receive thread only: the short window's SYNC stamps
        self._syncs_long: deque[float] = deque()  # receive thread only: the long window's
        self.sync_excess = (0, 0.0)  # (SYNC frames seen, own period gives) in the last window over the rate
        self.host_twin = 0.0
        self.nmt: dict[tuple[int, int], float] = {}  # (target node (0: all), command) -> when
        self.sdo: dict[int, float] = {}  # node -> when another client sent it an SDO request
        #: node -> when an RPDO to it passed: only another master's before this driver sends any
        #: (read by :meth:`master_evidence`, the look before the first NMT command)
        self.rpdo: dict[int, float] = {}
        #: when the newest of what :meth:`evidence` reports came (SYNC, NMT, host twin, SDO): the
        #: supervisor asks for each drive at each of its periods, and nearly always nothing came
        self._newest = 0.0
        #: called (on the receive thread, never waits) at another master's first sign after
        #: FOREIGN_HOLD_S without one: the supervisor's wake, so that a quiet supervisor judges it
        #: now; within the hold it looks every period anyway (Supervisor.wait_s), so a flood of
        #: another master's frames does not wake it once a frame
        self._wake: Callable[[], None] = lambda: None

    @property
    def newest(self) -> float:
        return self._newest

    @newest.setter
    def newest(self, when: float) -> None:
        first = when - self._newest > FOREIGN_HOLD_S
        self._newest = when
        if first:
            self._wake()

    def set_wake(self, wake: Callable[[], None]) -> None:
        """The supervisor: ``wake()`` (on the receive thread, never waits) when another master's sign comes."""
        self._wake = wake

    def set_own_sync(self, period_s: float) -> None:
        """The bus handle: this driver's SYNC reaches this listener at this period (0: it does not)."""
        self.own_sync_period_s = period_s

    def set_marks_local_frames(self, marks: bool) -> None:
        """The bus handle: the bus marks frames made on this host (SocketCAN's is_rx)."""
        self.marks_local_frames = marks
    def on_message_received(self, msg: can.Message) -> None:
        if not (msg.is_error_frame or msg.is_extended_id):
            self.on_frame(msg.arbitration_id, msg.data, msg.timestamp, msg.is_rx)

    def on_frame(self, cob: int, data: bytes | bytearray, timestamp: float, is_rx: bool = True) -> None:
        """An 11-bit data frame (its bus stamp; ``is_rx``: received from the wire, as SocketCAN marks it)."""
        if cob == 0x080:
            now = time.monotonic()
            period = self.own_sync_period_s
            if period <= 0 or (self.marks_local_frames and is_rx):
                self.sync = self.newest = now
                return
            # counted by the bus's timestamps, not by arrival: a busy process reads a burst of them
            wire = timestamp or time.time()
            syncs, long = self._syncs, self._syncs_long
            syncs.append(wire)
            long.append(wire)
            while wire - syncs[0] > SYNC_RATE_WINDOW_S:
                syncs.popleft()
            while wire - long[0] > SYNC_RATE_LONG_WINDOW_S:
                long.popleft()
            span = max(wire - long[0], SYNC_RATE_WINDOW_S)
            if len(syncs) > 1.5 * SYNC_RATE_WINDOW_S / period + 2 and \
                    len(long) > SYNC_RATE_LONG_FACTOR * span / period + 2:
                self.sync_excess = (len(syncs), SYNC_RATE_WINDOW_S / period)
                self.sync = self.newest = now
        elif cob == 0x000 and len(data) == 2:
            self.nmt[data[1], data[0]] = self.newest = time.monotonic()  # each kept: a reset then a start
        elif cob == FunctionCode.HEARTBEAT + self.host_node_id:
            self.host_twin = self.newest = time.monotonic()
        elif 0x601 <= cob <= 0x67F and cob - 0x600 in self.node_ids and data and data[0] & 0xE0 == 0x20:
            self.sdo[cob - 0x600] = self.newest = time.monotonic()  # a download (write); bench reads are harmless
        elif 0x200 <= cob < 0x580 and not cob & 0x80 and cob & 0x7F in self.node_ids:
            self.rpdo[cob & 0x7F] = time.monotonic()  # RPDO1-4 (0x200, 0x300, 0x400, 0x500 + node)

    def evidence(self, node_id: int, since: float) -> str:
        """What shows another master acting on ``node_id`` after ``since`` ('' when nothing)."""
        if self.newest <= since:
            return ""  # nothing of it came since: the supervisor's usual answer, without building one
        return self._evidence(node_id, since)

    def _evidence(self, node_id: int, since: float) -> str:
        found = []
        if self.host_twin > since:
            found.append(f"heartbeats of node {self.host_node_id}, this driver's own id: a second driver?")
        if self.sync > since:
            count, own = self.sync_excess
            more = f" ({count} in {SYNC_RATE_WINDOW_S:g} s where its own give {own:.0f})" if count else ""
            found.append(f"SYNC frames this driver did not send{more}")  # or more of them than it sends
        seen = list(self.nmt.items())  # one copy (the receive thread may add a key meanwhile)
        for (target, command), when in sorted(seen, key=lambda item: item[1]):
            if target in (node_id, 0) and when > since:
                found.append(f"NMT command 0x{command:02X} to {'all nodes' if target == 0 else f'node {target}'}")
        if self.sdo.get(node_id, 0.0) > since:
            found.append(f"SDO writes to node {node_id} from another client")
        return "; ".join(found)


    def master_evidence(self, since: float) -> str:
        """What shows a live master on the bus after ``since``, for any of this driver's drives
        ('' when nothing): the look before a first NMT command, when none of it can be this
        driver's own."""
        found = [self.evidence(node, since) for node in sorted(self.node_ids)]
        found += [f"RPDOs to node {node}" for node, when in sorted(self.rpdo.items()) if when > since]
        unique = list(dict.fromkeys(part for text in found for part in text.split("; ") if part))
        return "; ".join(unique)


def look_for_master(bus: can.BusABC, host_node_id: int, node_ids: Collection[int], seconds: float) -> str:
    """Listen on ``bus`` for ``seconds`` before anything is sent to it; the evidence of another
    live master ('' when none): its heartbeat with the host id, SYNC, NMT commands, RPDOs or SDO
    writes to ``node_ids``. For a bus of its own (a bench command); the driver keeps a listener."""
    foreign = ForeignTraffic(host_node_id, node_ids)
    since = time.monotonic()
    deadline = since + seconds
    while (remaining := deadline - time.monotonic()) > 0:
        msg = bus.recv(remaining)
        if msg is not None:
            foreign.on_message_received(msg)
    return foreign.master_evidence(since - 1.0)


def other_master_error(where: str, evidence: str) -> ForeignMasterError:
    return ForeignMasterError(f"{where}: another master is live on the bus ({evidence}); nothing was sent. Two"
                              " masters on one drive fight over it: stop the other driver or tool first. To take"
                              " the bus over anyway (its drives are reset and disarmed): --force on the bench,"
                              " MotorDriver.start(take_over=True) in Python.", evidence=evidence)


def look_window_s(host_heartbeat_s: float) -> float:
    return max(LOOK_MIN_S, 2.0 * host_heartbeat_s)
