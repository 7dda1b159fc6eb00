"""The flight recorder: the last seconds of every frame and drive state, kept in memory and
written when something goes wrong, so that a field incident can be read and replayed.

An incident is an EMCY, a drive's heartbeat lost, a watchdog stop, a bus lost, or a drive
found at boot to have stopped itself because the host was gone (EMCY 0x8130 in its error
history). Each writes, into the configured directory (capped in size, oldest first):

- ``<stamp>-<kind>-<who>.blf``: the frames of every bus, received and sent (python-can's BLF;
  the JSON names the bus of each BLF channel),
- ``<stamp>-<kind>-<who>.json``: the summary (``rovercan incident FILE`` prints it),
- ``<stamp>-<kind>-<who>.png``: angle, velocity, torque and state of every drive around it,
  drawn by a helper process at low priority (``python -m motor_driver.recording FILE.json``,
  :mod:`.plot`) from the states the JSON carries: matplotlib in the driver's process would hold
  its interpreter for a second or more, and the host heartbeat with it. While the process is
  starved (its host heartbeat went out late within NO_PLOT_AFTER_LATE_S) the plot waits until it
  is not, or until close(); an incident without drive states says why it has no plot. A helper
  that finished is reaped at the writer's next poll (no zombie child while the driver runs);
  close() gives the helpers still drawing PLOT_WAIT_S in all, then terminates them.

The ring is bounded by time (``seconds`` + ``after_s``) and by count: each bus keeps at most
what it can carry at its full rate for that window (:func:`frames_cap`: its bitrate over
FULL_RATE_FRAME_BITS, the length of an 8-byte frame). A babbling node on a bus faster than its
bitrate (the emulator: 345,200 EMCYs in 10 s grew the driver by 120 MB when only time bounded it)
or of shorter frames pushes the oldest frames out early: each is counted (``dropped``), said in a
WARNING (rate-limited) and in the next incident written (``frames_dropped``, ``frames_cap``).

Threads and what each owns: the buses' receive threads append received frames to their bus's
ring and flag an EMCY as an incident (a queue put); command threads append the frames they send
the same way; the supervisor appends drive-state samples and flags its own incidents. A bus's
ring is one buffer of fixed-size slots (22 bytes a frame, not watched by the garbage collector;
a bytes object a frame cost 64) allocated at its count bound, written in place under the ring's own lock, which its appenders
and the writer hold only to write or copy slots and indexes (:class:`_Ring`): no frame is torn or
lost between two appenders, no count of ``dropped`` is lost. The writer thread
(``rovercan-recorder``) waits ``after_s`` so that what follows is kept, copies the rings (under
each ring's lock: whole slots of one instant) and writes the files from its copy, a frame unpacked
at a time; each of its passes is supervised (an exception is logged and counted in
``writer_errors``, the thread goes on). Nothing waits on the writer, and no lock is shared with
the bus.

What lives where: this module (the ring, the incidents, the writer thread),
:mod:`.incident_mcap` (an incident's frames as MCAP beside its BLF), :mod:`.plot` (its PNG,
drawn by the helper process :mod:`.__main__`), :mod:`.incident` (an incident read back: the
summary, the frames, the fault steps of a scenario) and :mod:`.recording` (any CAN recording
read, each frame checked).
"""

from __future__ import annotations

import json
import logging
import math
import os
import queue
import struct
import subprocess
import sys
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import asdict, dataclass
from heapq import merge
from itertools import islice
from pathlib import Path
from typing import Any, overload

import can

from can_config.config import RecorderConfig
from can_config.model import RoverConfig
from can_config.objects import emcy_text
from can_config.realtime import ordinary_thread
from motor_driver.drive import DriveState
from motor_driver.process.ratelimit import RateLimitedLog
from motor_driver.recording.busview import UnitObjects
from motor_driver.recording.incident import FORMAT
from motor_driver.recording.incident_mcap import write_incident_mcap
from motor_driver.recording.plot import plot_incident, state_series

__all__ = ["INCIDENT_KINDS", "FlightRecorder", "Frame", "IncidentEvent", "frames_cap", "plot_incident"]

logger = logging.getLogger(__name__)

#: One kept frame: time.time(), bus name, COB-ID, extended, remote, error frame, DLC, data.
Frame = tuple[float, str, int, bool, bool, bool, int, bytes]

INCIDENT_KINDS = ("emcy", "heartbeat_lost", "watchdog_stop", "bus_lost", "host_loss_stop")
#: How often the writer looks for the stop of the driver while it waits.
WRITER_POLL_S = 0.2
#: The drives' states are kept every SAMPLE_PERIOD_S (20 Hz): at the supervisor's first pass at most
#: SAMPLE_EARLY_S before it is due (its pass, not a wake of its own: it rides the supervisor's cadence).
SAMPLE_PERIOD_S = 0.05
SAMPLE_EARLY_S = 0.005
#: The same EMCY of a node again within this long is no new incident (the frames are kept all the same).
EMCY_REPEAT_S = 1.0
#: close() waits this long, in all, for the plots still being drawn; a helper still drawing then
#: is terminated (killed TERMINATE_WAIT_S later): the PNG is missing, the JSON still draws it.
PLOT_WAIT_S = 5.0
TERMINATE_WAIT_S = 1.0
#: The plot helper's command, the incident's JSON appended (tests hold it with a command of theirs).
PLOT_COMMAND: tuple[str, ...] = (sys.executable, "-m", "motor_driver.recording")
#: An incident of the kind and drive (or bus) of one written within this long is counted in
#: the next one written instead: a flapping drive makes one incident a minute, not one a second.
REPEAT_WINDOW_S = 60.0
#: No plot process is started within this long of the host heartbeat going out late (a starved
#: process gets no third process beside it).
NO_PLOT_AFTER_LATE_S = 30.0
#: Incidents kept in memory (their summaries) when the directory cannot be written.
KEPT_IN_MEMORY = 20
#: The bits of one 8-byte standard frame on the wire, interframe space included, no stuffing: a
#: bus at its full rate of such frames (a babbling node's EMCYs) is what each bus's ring holds.
FULL_RATE_FRAME_BITS = 111
#: A bus the recorder has no config for is taken to run at this bitrate.
DEFAULT_BITRATE = 1_000_000
#: One kept frame, a fixed-size slot of its bus's ring: time.time(), COB-ID, flags (extended 1,
#: remote 2, error 4, sent by this driver 8; the data's length in the upper four bits), DLC, data
#: (classic CAN: 8 bytes at most, the rest of a longer frame's is not kept).
_SLOT = struct.Struct("<dIBB8s")
_SLOT_SIZE = _SLOT.size  # 22 bytes
_EXTENDED, _REMOTE, _ERROR, _SENT = 1, 2, 4, 8
_DATA_MAX = 8
_time_at = struct.Struct("<d").unpack_from  # a slot's time.time()
#: An incident's frames in time order are merged from at most this many runs of a bus's frames (each
#: in time order) at once; a bus of more (clocks that disagree within one stream) is merged in passes.
MERGE_FAN_IN = 16


def frames_cap(bitrate: int, window_s: float) -> int:
    """The frames one bus's ring keeps at most: what the bus carries in ``window_s`` at its full
    rate of 8-byte frames."""
    return max(1, math.ceil(bitrate / FULL_RATE_FRAME_BITS * window_s))


class _Frames(Sequence[Frame]):
    """An incident's frames: each bus's ring as copied (its slots, oldest first), unpacked one at a
    time as a writer reads them, the buses merged (each bus's in arrival order; :meth:`in_time`:
    every frame in time order). No object per frame lives longer than the writer's look at it, and
    the time order is made without a sort key per frame (writing the full rings of a babbling node's
    storm once took 20 MB of small objects in the driver, its heap fragmented after)."""

    def __init__(self, per_bus: Sequence[tuple[str, bytes | memoryview]]) -> None:
        self._per_bus = [(bus, slots) for bus, slots in per_bus if slots]
        self._count = sum(len(slots) // _SLOT_SIZE for _, slots in self._per_bus)
        self.buses = [bus for bus, _ in self._per_bus]

    def __len__(self) -> int:
        return self._count

    def __iter__(self) -> Iterator[Frame]:
        return merge(*(_unpacked(bus, slots) for bus, slots in self._per_bus), key=_frame_time)

    def in_time(self) -> Iterator[Frame]:
        """Every frame in time order: each bus's runs in time order (:func:`_runs_in_time`), merged."""
        return merge(*(run for bus, slots in self._per_bus for run in _runs_in_time(bus, slots)), key=_frame_time)

    @overload
    def __getitem__(self, index: int) -> Frame: ...

    @overload
    def __getitem__(self, index: slice) -> list[Frame]: ...

    def __getitem__(self, index: int | slice) -> Frame | list[Frame]:
        if isinstance(index, slice):
            return list(self)[index]
        if index in (0, -1) and self._count:  # the first and the last: one look per bus
            ends = [next(_unpacked(bus, slots[-_SLOT_SIZE:] if index else slots[:_SLOT_SIZE])) for bus, slots in self._per_bus]
            return min(ends) if index == 0 else max(ends)
        if not -self._count <= index < self._count:
            raise IndexError(index)
        return next(islice(iter(self), index % self._count, None))


def _frame_time(frame: Frame) -> float:
    return frame[0]


def _unpacked(bus: str, slots: bytes | bytearray | memoryview, mask: int = 0, want: int = 0) -> Iterator[Frame]:
    """The frames of ``slots`` (whole slots, in their order) whose flags masked by ``mask`` are ``want``."""
    for t, cob, flags, dlc, data in _SLOT.iter_unpack(slots):
        if flags & mask == want:
            yield (t, bus, cob, bool(flags & _EXTENDED), bool(flags & _REMOTE), bool(flags & _ERROR), dlc,
                   data[:flags >> 4])


#: A run of one bus's slots: (mask, want, first byte, end byte): the slots in [first, end) whose
#: flags masked by ``mask`` are ``want``, in time order.
_Run = tuple[int, int, int, int]


def _runs_in_time(bus: str, slots: bytes | memoryview) -> list[Iterator[Frame]]:
    """One bus's frames (slots in arrival order) as at most MERGE_FAN_IN iterators, each in time order.

    The frames the bus's receive thread appends carry the bus's stamps, which its single thread
    takes in order; the frames this driver sends are stamped as they are appended (:meth:`FlightRecorder._push`,
    under the ring's lock), so each is in time order alone. Between the two they are not: a bus's
    stamps come from its interface's clock (socketcand's server, the kernel), and the sent frames
    sit between received ones stamped later than they. So the two streams are read apart, each
    split where its time goes back (a clock stepped): a few runs, merged by time without a key per
    frame. A bus of more runs than MERGE_FAN_IN is merged in passes into new buffers first."""
    runs = _runs(slots)
    buffer: bytes | bytearray | memoryview = slots
    while len(runs) > MERGE_FAN_IN:
        buffer, runs = _merged(buffer, runs)
    view = memoryview(buffer)
    return [_unpacked(bus, view[first:end], mask, want) for mask, want, first, end in runs]


def _runs(slots: bytes | bytearray | memoryview) -> list[_Run]:
    """The runs in time order of a bus's received frames and of its sent frames, in one pass."""
    runs: list[_Run] = []
    first = [-1, -1]  # byte where the current run of the received (0) and the sent (1) frames began
    last = [-math.inf, -math.inf]
    at = 0
    for t, _, flags, _, _ in _SLOT.iter_unpack(slots):
        sent = 1 if flags & _SENT else 0
        if t < last[sent]:
            runs.append((_SENT, flags & _SENT, first[sent], at))
            first[sent] = at
        elif first[sent] < 0:
            first[sent] = at
        last[sent] = t
        at += _SLOT_SIZE
    runs.extend((_SENT, _SENT if sent else 0, first[sent], at) for sent in (0, 1) if first[sent] >= 0)
    return runs


def _merged(slots: bytes | bytearray | memoryview, runs: list[_Run]) -> tuple[bytearray, list[_Run]]:
    """One merge pass: every MERGE_FAN_IN runs of ``slots`` into one, in a new buffer."""
    out = bytearray()
    merged: list[_Run] = []
    view = memoryview(slots)
    for i in range(0, len(runs), MERGE_FAN_IN):
        first = len(out)
        for _, at in merge(*(_times(view, *run) for run in runs[i:i + MERGE_FAN_IN])):
            out += view[at:at + _SLOT_SIZE]
        merged.append((0, 0, first, len(out)))
    return out, merged


def _times(view: memoryview, mask: int, want: int, first: int, end: int) -> Iterator[tuple[float, int]]:
    at = first
    for t, _, flags, _, _ in _SLOT.iter_unpack(view[first:end]):
        if flags & mask == want:
            yield t, at
        at += _SLOT_SIZE


class _Ring:
    """One bus's frames: one buffer of fixed-size slots (_SLOT), allocated at the ring's count bound
    (what the bus carries at its full rate in the window: a bounded cost known at start, not one
    that grows with the traffic), written in a circle, ``end`` where the next frame goes (the
    oldest's slot once ``count`` is the bound). The time window is applied as the ring is read
    (:func:`_in_window`); a frame is pushed out before its time, and counted, when its slot is
    written while it is within the window.

    Several threads append (the bus's receive thread, every thread that sends on it) and the writer
    copies: each holds ``lock`` for all it reads or writes of the buffer, ``end``, ``count`` and
    ``dropped``, and does nothing else while it does (no I/O, no other lock taken). So two appenders
    never write one slot or lose an index update, a count of ``dropped`` is never lost, and the
    writer's copy is whole slots and one instant's ``end``, ``count`` and ``dropped``: it reads no
    slot an appender is writing. ``said`` is the writer's alone."""

    __slots__ = ("cap", "count", "dropped", "end", "lock", "nbytes", "said", "slots")

    def __init__(self, cap: int) -> None:
        self.cap = cap
        self.nbytes = cap * _SLOT_SIZE
        self.slots = bytearray(self.nbytes)
        self.end = 0  # the byte where the next frame goes
        self.count = 0  # slots written, up to cap
        self.dropped = 0  # pushed out by the count bound before their time, since the start
        self.said = 0  # of them, named in an incident written already (writer thread)
        self.lock = threading.Lock()

    def snapshot(self) -> tuple[bytes, int]:
        """A copy of the slots written, oldest first, and the count dropped up to the same instant."""
        with self.lock:
            view = memoryview(self.slots)
            if self.count < self.cap:
                return view[:self.end].tobytes(), self.dropped
            return b"".join((view[self.end:], view[:self.end])), self.dropped


def _in_window(slots: bytes, keep_s: float) -> memoryview:
    """A ring's copy without its frames older than the window: those before the first one within
    ``keep_s`` of its newest frame (a frame of an older stamp behind a newer one stays, as it came)."""
    if not slots:
        return memoryview(slots)
    horizon = max(t for t, _, _, _, _ in _SLOT.iter_unpack(slots)) - keep_s
    first = 0
    for t, _, _, _, _ in _SLOT.iter_unpack(slots):
        if t >= horizon:
            break
        first += _SLOT_SIZE
    return memoryview(slots)[first:]


@dataclass(frozen=True)
class IncidentEvent:
    """One thing that went wrong: ``t`` is time.time(), like the frames' timestamps."""

    kind: str
    t: float
    bus: str
    node: int | None = None
    drive: str | None = None
    code: int | None = None
    text: str = ""


class _BusTap(can.Listener):
    """Received frames of one bus into the ring (the bus's receive thread)."""

    def __init__(self, recorder: FlightRecorder, bus: str) -> None:
        self.recorder = recorder
        self.bus = bus
        self._emcy_said: dict[int, tuple[int, float]] = {}  # node -> (code, when) of its last EMCY incident

    def on_message_received(self, msg: can.Message) -> None:
        self.recorder.append(self.bus, msg)
        if not msg.is_extended_id:
            self._emcy(msg.arbitration_id, msg.data, msg.timestamp)

    def on_read(self, frames: Sequence[tuple[int, bytes | bytearray, float, int]]) -> None:
        """The frames of one batch read, as it took them ((cob, data, stamp, flags); flags as the
        ring stores them): into the ring under one take of its lock, then each EMCY looked at."""
        self.recorder._push_read(self.bus, frames)
        for cob, data, t, flags in frames:
            if 0x081 <= cob <= 0x0FF and not flags & _EXTENDED:
                self._emcy(cob, data, t)

    def _emcy(self, cob: int, data: bytes | bytearray, t: float) -> None:
        if 0x081 <= cob <= 0x0FF and len(data) >= 3:
            code = int.from_bytes(data[:2], "little")
            said_code, said_at = self._emcy_said.get(cob, (0, -EMCY_REPEAT_S))
            now = time.monotonic()
            if code and (code != said_code or now - said_at >= EMCY_REPEAT_S):  # a babbling node: one a second
                self._emcy_said[cob] = (code, now)
                self.recorder.trigger("emcy", self.bus, node=cob - 0x80, code=code, text=emcy_text(code),
                                      t=t or time.time())


class FlightRecorder:
    """A bounded ring of frames and drive states, written on each incident. ``close()`` writes
    what is pending and stops the writer; it is idempotent."""

    def __init__(self, config: RecorderConfig, drives: Mapping[str, tuple[str, int]],
                 bus_channels: Mapping[str, str], source: Path | None = None, rover: RoverConfig | None = None,
                 unit_objects: Callable[[], Mapping[str, UnitObjects]] | None = None) -> None:
        """``rover``: the config the drives are decoded by in the incident's .mcap (without it, the
        .mcap holds the raw frames only); ``unit_objects``: each drive's unit objects as the driver
        read them at boot, which the .mcap is decoded by and holds in its metadata."""
        self.config = config
        self._rover = rover
        self._unit_objects = unit_objects
        self._bus_channels = dict(bus_channels)
        self.directory = config.directory
        self._names = {(bus, node): name for name, (bus, node) in drives.items()}
        self._keep_s = config.seconds + config.after_s
        # a frame is kept as one slot of its bus's buffer (see _SLOT), not a can.Message: the garbage
        # collector does not watch it, so 10 s of frames (50,000 at 6 drives) cost nothing in its
        # full collections, which stop every thread of the process; as can.Messages they made one
        # take 70 ms and the host heartbeat went out 110 ms late
        bitrates = {b.name: b.bitrate for b in rover.buses} if rover is not None else {}
        self._rings = {bus: _Ring(frames_cap(bitrates.get(bus, DEFAULT_BITRATE), self._keep_s))
                       for bus in {*self._bus_channels, *bitrates}}
        self._rings_lock = threading.Lock()  # a bus first heard that has no ring yet (rare)
        self._said_drops = RateLimitedLog(logger)
        self._drops_logged: dict[str, int] = {}  # bus -> its dropped count when last looked at (writer)
        self.writer_errors = 0  # writer passes that raised (writer thread)
        self._states: deque[tuple[float, tuple[DriveState, ...]]] = deque()
        self._events: queue.SimpleQueue[IncidentEvent] = queue.SimpleQueue()
        self._stop = threading.Event()
        self._source = source
        self.written: list[Path] = []  # the JSON of each incident written (writer thread)
        #: plot processes: started by whichever thread writes an incident (the writer; a tool or a test
        #: calling write()), reaped by the writer, ended by close(): each look at the list is under the lock
        self._helpers: list[subprocess.Popen[bytes]] = []
        self._helpers_lock = threading.Lock()
        self._deferred: list[Path] = []  # incidents whose plot waits for the process to be on time (writer)
        self._sampled_at = -math.inf  # when the supervisor's pass last sampled the drives (monotonic)
        self._late_at = -math.inf  # monotonic time the host heartbeat was last late (process_late)
        self._last_written: dict[tuple[str, str], float] = {}  # (kind, drive or bus) -> its t (writer)
        self._repeats: dict[tuple[str, str], int] = {}  # incidents not written since (writer)
        self.kept: deque[dict[str, Any]] = deque(maxlen=KEPT_IN_MEMORY)  # summaries not written (writer)
        self._unwritable_said = False
        self._thread = threading.Thread(target=self._run, daemon=True, name="rovercan-recorder")
        self._thread.start()

    # ------------------------------------------------------------------ recording (many threads)
    def listener(self, bus: str) -> _BusTap:
        return _BusTap(self, bus)

    def append(self, bus: str, msg: can.Message, sent: int = 0) -> None:
        """A frame received on ``bus`` (``sent``: _SENT for one this driver sent)."""
        flags = (_EXTENDED if msg.is_extended_id else 0) | (_REMOTE if msg.is_remote_frame else 0) \
            | (_ERROR if msg.is_error_frame else 0) | sent
        self._push(bus, msg.timestamp, msg.arbitration_id, flags, msg.dlc, msg.data)

    def record_sent(self, bus: str, msg: can.Message) -> None:
        """A frame this driver sent (without a timestamp: stamped now)."""
        self.append(bus, msg, _SENT)

    def record_frame(self, bus: str, can_id: int, data: bytes | bytearray, remote: bool = False) -> None:
        """A frame this driver sent, as canopen hands it to the bus (GuardedNetwork.on_sent):
        kept without a can.Message made for it (every command's RPDO comes this way), stamped now."""
        self._push(bus, 0.0, can_id, (_EXTENDED if can_id > 0x7FF else 0) | (_REMOTE if remote else 0) | _SENT,
                   len(data), data)

    def _push(self, bus: str, t: float, cob: int, flags: int, dlc: int, data: bytes | bytearray) -> None:
        """One frame into its bus's ring, ``t`` 0 for one stamped now: under the ring's lock, so a
        bus's frames stamped here are in time order as they are in the ring (see :func:`_runs_in_time`).
        A full ring's oldest frame gives its slot: counted if it is within the window still."""
        ring = self._rings.get(bus) or self._new_ring(bus)
        length = len(data)
        if length > _DATA_MAX:  # noqa: PLR1730 (min() costs a call a frame)
            length = _DATA_MAX
        lock = ring.lock
        lock.acquire()  # (not `with`: a third cheaper; nothing in here raises but a bad frame's packing)
        try:
            if not t:
                t = time.time()
            end = ring.end
            full = ring.count == ring.cap
            early = full and _time_at(ring.slots, end)[0] >= t - self._keep_s  # pushed out before its time
            _SLOT.pack_into(ring.slots, end, t, cob, flags | length << 4, dlc, data)  # first: a frame that
            if early:  # does not pack changes no count
                ring.dropped += 1
            elif not full:
                ring.count += 1
            end += _SLOT_SIZE
            ring.end = end if end < ring.nbytes else 0
        finally:
            lock.release()

    def _push_read(self, bus: str, frames: Sequence[tuple[int, bytes | bytearray, float, int]]) -> None:
        """The frames of one read ((cob, data, stamp, flags)) into their bus's ring, as :meth:`_push`
        does each, under one take of the ring's lock (once a read, not once a frame: issue 72)."""
        ring = self._rings.get(bus) or self._new_ring(bus)
        slots, cap, nbytes, keep_s, pack = ring.slots, ring.cap, ring.nbytes, self._keep_s, _SLOT.pack_into
        lock = ring.lock
        lock.acquire()
        end, count, dropped = ring.end, ring.count, ring.dropped
        try:
            for cob, data, stamp, flags in frames:
                length = len(data)
                t = stamp or time.time()
                full = count == cap
                early = full and _time_at(slots, end)[0] >= t - keep_s
                pack(slots, end, t, cob, flags | (length if length < _DATA_MAX else _DATA_MAX) << 4, length, data)
                if early:
                    dropped += 1
                elif not full:
                    count += 1
                end += _SLOT_SIZE
                if end >= nbytes:
                    end = 0
        finally:  # a frame that does not pack changes no count: those before it are kept
            ring.end, ring.count, ring.dropped = end, count, dropped
            lock.release()

    def _new_ring(self, bus: str) -> _Ring:
        with self._rings_lock:
            return self._rings.setdefault(bus, _Ring(frames_cap(DEFAULT_BITRATE, self._keep_s)))

    def dropped(self) -> dict[str, int]:
        """Frames each bus's count bound pushed out of the ring before their time, since the start
        (diagnostics, tests)."""
        return {bus: ring.dropped for bus, ring in list(self._rings.items())}

    def frames_kept(self) -> int:
        """Frames in the rings' windows now (tests, tools: each ring read)."""
        return sum(len(_in_window(ring.snapshot()[0], self._keep_s)) // _SLOT_SIZE for ring in list(self._rings.values()))

    def wants_sample(self, now: float) -> bool:
        """Supervisor: whether its pass at ``now`` (monotonic) should call :meth:`sample`: about every
        SAMPLE_PERIOD_S, whatever the supervisor's period (at most SAMPLE_EARLY_S early)."""
        if now - self._sampled_at < SAMPLE_PERIOD_S - SAMPLE_EARLY_S:
            return False
        self._sampled_at = now
        return True

    def sample(self, states: Sequence[DriveState]) -> None:
        """Supervisor: the drives' states now."""
        now = time.time()
        self._states.append((now, tuple(states)))
        while self._states and self._states[0][0] < now - self._keep_s:
            self._states.popleft()

    def process_late(self) -> None:
        """Supervisor: the host heartbeat went out late (this process is starved)."""
        self._late_at = time.monotonic()

    def trigger(self, kind: str, bus: str, *, node: int | None = None, drive: str | None = None,
                code: int | None = None, text: str = "", t: float | None = None) -> None:
        if drive is None and node is not None:
            drive = self._names.get((bus, node))
        self._events.put(IncidentEvent(kind, t or time.time(), bus, node, drive, code, text))

    # ------------------------------------------------------------------ writer thread
    def _run(self) -> None:
        while not self._stop.is_set():
            self._supervised(self._pass)
        rest: list[IncidentEvent] = []
        while True:
            try:
                rest.append(self._events.get_nowait())
            except queue.Empty:
                break
        if rest:
            self._supervised(lambda: self._write_safely(rest))
        self._supervised(self._plot_deferred)  # the driver stops: what waited is drawn now

    def _supervised(self, step: Callable[[], None]) -> None:
        """One pass of the writer: an exception is logged with its traceback and counted, and the
        writer goes on (issue 70: the plot reaper raised outside any handler and the thread died)."""
        try:
            step()
        except Exception:  # the recorder must never take the driver down, nor stop recording
            self.writer_errors += 1
            logger.exception("flight recorder: the writer's pass failed (%d so far); it goes on", self.writer_errors)

    def _pass(self) -> None:
        """Wait for an incident (reap the plot helpers, say the drops, draw deferred plots meanwhile),
        then for ``after_s`` more of it, and write it."""
        try:
            first = self._events.get(timeout=WRITER_POLL_S)
        except queue.Empty:
            self._reap()
            self._say_drops()
            if self._deferred and time.monotonic() - self._late_at > NO_PLOT_AFTER_LATE_S:
                self._plot_deferred()
            return
        events = [first]
        deadline = time.monotonic() + self.config.after_s
        while (left := deadline - time.monotonic()) > 0 and not self._stop.is_set():
            try:  # what happens meanwhile is the same incident
                events.append(self._events.get(timeout=min(left, WRITER_POLL_S)))
            except queue.Empty:
                pass
        self._write_safely(events)

    def _say_drops(self) -> None:
        """A WARNING (one per bus every PERIOD_S) while a bus's count bound pushes frames out."""
        for bus, ring in list(self._rings.items()):
            if ring.dropped > self._drops_logged.get(bus, 0):
                self._drops_logged[bus] = ring.dropped
                self._said_drops.log(logging.WARNING, bus, "flight recorder: bus %s: %d frame(s) dropped from the ring"
                                     " so far: more than the bus carries at its full rate in %.0f s (%d frames);"
                                     " a babbling node? (the incidents say how many each lost)",
                                     bus, ring.dropped, self._keep_s, ring.cap)

    def _plot_deferred(self) -> None:
        for json_path in self._deferred:
            self._plot_in_helper(json_path)
        self._deferred = []

    def _write_safely(self, events: list[IncidentEvent]) -> None:
        first = events[0]
        key = (first.kind, first.drive or first.bus)
        if first.t - self._last_written.get(key, -math.inf) < REPEAT_WINDOW_S:
            self._repeats[key] = self._repeats.get(key, 0) + 1
            logger.debug("flight recorder: %s (%s) again within %.0f s: counted, not written", *key, REPEAT_WINDOW_S)
            return
        self._last_written[key] = first.t
        try:
            self.written.append(self.write(events, self._repeats.pop(key, 0)))
        except OSError as err:  # a read-only root, a full disk: say it once, keep the incident here
            if not self._unwritable_said:
                self._unwritable_said = True
                logger.warning("flight recorder: cannot write incidents to %s (%s); the last %d are kept in memory"
                               " instead. Set recorder.dir in the config (or $ROVERCAN_INCIDENT_DIR) to a writable"
                               " directory.", self.directory, err.strerror or err, KEPT_IN_MEMORY)
        except Exception:  # the recorder must never take the driver down
            logger.exception("flight recorder: the incident %s could not be written", first.kind)

    def write(self, events: list[IncidentEvent], repeats: int = 0) -> Path:
        """Write one incident (the ring as it is now); returns the JSON's path. ``repeats``:
        incidents of its kind and drive counted, not written, since the last one. Its summary is
        kept in memory first, so an unwritable directory (OSError) loses nothing recent."""
        first = events[0]
        frames, dropped = self._take_frames()
        states = list(self._states.copy())
        summary_kept: dict[str, Any] = {"kind": first.kind, "t": first.t, "events": [asdict(e) for e in events],
                                        "repeats": repeats, "frames": len(frames), "frames_dropped": dropped}
        self.kept.append(summary_kept)
        self.directory.mkdir(parents=True, exist_ok=True)
        stamp = time.strftime("%Y%m%d-%H%M%S", time.localtime(first.t)) + f"-{int(first.t * 1000) % 1000:03d}"
        who = first.drive or (f"node{first.node}" if first.node is not None else first.bus)
        base = self.directory / f"{stamp}-{first.kind}-{who}"
        buses = sorted(set(frames.buses) | {e.bus for e in events})
        channel_of = {bus: i + 1 for i, bus in enumerate(buses)}
        _write_blf(base.with_suffix(".blf"), frames, channel_of)
        summary: dict[str, Any] = {
            "format": FORMAT,
            "kind": first.kind,
            "time": time.strftime("%Y-%m-%dT%H:%M:%S", time.localtime(first.t)),
            "t": first.t,
            "events": [asdict(e) for e in events],
            "repeats": repeats,
            "window_s": [frames[0][0] - first.t, frames[-1][0] - first.t] if frames else [0, 0],
            "frames": len(frames),
            "frames_dropped": dropped,
            "frames_cap": {bus: ring.cap for bus, ring in list(self._rings.items())},
            "channels": {str(i): bus for bus, i in channel_of.items()},
            "bus_channels": self._bus_channels,
            "drives": [{"name": name, "bus": bus, "node_id": node} for (bus, node), name in self._names.items()],
            "config": str(self._source) if self._source else None,
            "blf": base.with_suffix(".blf").name,
            "mcap": None,
            "png": None,
        }
        summary["states"] = state_series(states, first.t)
        json_path = base.with_suffix(".json")
        self._write_mcap(base.with_suffix(".mcap"), frames, events, summary)
        late = time.monotonic() - self._late_at <= NO_PLOT_AFTER_LATE_S
        plot = self.config.plot and bool(summary["states"])
        if plot:
            summary["png"] = base.with_suffix(".png").name  # drawn by a helper process, below
            if late:
                summary["plot_deferred"] = (f"the host heartbeat went out late within {NO_PLOT_AFTER_LATE_S:.0f} s:"
                                            " drawn once it has been on time that long, or when the driver stops")
        else:  # why there is none (`python -m motor_driver.recording INCIDENT.json` still draws what it can)
            summary["plot_skipped"] = ("plot: false in the recorder config" if not self.config.plot else
                                       "no drive states recorded")
        json_path.write_text(json.dumps(summary, indent=1) + "\n")
        self.kept.remove(summary_kept)
        if plot and late:
            self._deferred.append(json_path)
        elif plot:
            self._plot_in_helper(json_path)
        lost = "".join(f"; bus {bus}: {n} frame(s) dropped from the ring (count bound, a babbling node?)"
                       for bus, n in dropped.items() if n)
        logger.warning("flight recorder: %s (%s) written to %s%s", first.kind, who, json_path, lost)
        _enforce_cap(self.directory, self.config.max_mb * 1e6, keep=base.name)
        return json_path

    def _take_frames(self) -> tuple[_Frames, dict[str, int]]:
        """Writer: a copy of every bus's ring now (unpacked as read, in time order: :class:`_Frames`),
        and the frames each bus's count bound dropped since the last incident written (then counted
        as said), of the same instant as the copy."""
        per_bus: list[tuple[str, memoryview]] = []
        dropped: dict[str, int] = {}
        for bus, ring in list(self._rings.items()):
            slots, total = ring.snapshot()
            per_bus.append((bus, _in_window(slots, self._keep_s)))
            dropped[bus], ring.said = total - ring.said, total
        return _Frames(per_bus), dropped

    def _write_mcap(self, path: Path, frames: Sequence[Frame], events: list[IncidentEvent], summary: dict[str, Any]) -> None:
        """The incident's .mcap (named in ``summary``): a failure costs it alone, not the BLF and JSON."""
        told = [(e.t, e.drive or e.bus, f"incident {e.kind}" + (f": 0x{e.code:04X}" if e.code is not None else "")
                 + (f" {e.text}" if e.text else "")) for e in events]
        metadata = {"incident": summary["kind"], "time": summary["time"], "config": summary["config"] or ""}
        try:
            units = self._unit_objects() if self._unit_objects is not None else {}
            write_incident_mcap(path, frames, told, self._rover, metadata, units)
        except OSError:
            raise  # the directory: handled as the BLF's
        except Exception:
            logger.exception("flight recorder: the incident's .mcap could not be written (its .blf is)")
            path.unlink(missing_ok=True)
            return
        summary["mcap"] = path.name

    def _plot_in_helper(self, json_path: Path) -> None:
        """The PNG is drawn by a process of its own at low priority (ordinary scheduling, nice 10):
        matplotlib in this one would hold the interpreter for a second or two, and the supervisor's
        host heartbeat with it."""
        self._reap()
        with ordinary_thread():  # the helper takes this thread's scheduling: never the driver's SCHED_FIFO
            helper = subprocess.Popen([*PLOT_COMMAND, str(json_path)], stdin=subprocess.DEVNULL,
                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        with self._helpers_lock:
            self._helpers.append(helper)

    def _reap(self) -> None:
        """Writer: the helpers that finished are waited for (no zombie stays while the driver runs)."""
        with self._helpers_lock:  # a list rebuilt while another thread appended lost that helper
            self._helpers = [p for p in self._helpers if p.poll() is None]

    def helper_pids(self) -> list[int]:
        """The plot helpers not yet reaped (tests, tools)."""
        with self._helpers_lock:
            return [p.pid for p in self._helpers]

    def close(self) -> None:
        """Write what is pending, stop the writer, and end the plot helpers within PLOT_WAIT_S in all:
        one still drawing then is terminated, so a shutdown is bounded whatever is being drawn."""
        if self._stop.is_set():
            return
        self._stop.set()
        self._thread.join(timeout=30.0)
        deadline = time.monotonic() + PLOT_WAIT_S
        with self._helpers_lock:
            helpers, self._helpers = self._helpers, []
        for helper in helpers:  # none left running, none left a zombie
            try:
                helper.wait(timeout=max(0.0, deadline - time.monotonic()))
            except subprocess.TimeoutExpired:
                logger.warning("flight recorder: a plot was still being drawn after %.0f s (pid %d): stopped; draw it"
                               " with `python -m motor_driver.recording` and the incident's JSON", PLOT_WAIT_S,
                               helper.pid)
                _end_helper(helper)


def _write_blf(path: Path, frames: Iterable[Frame], channel_of: Mapping[str, int]) -> None:
    """An incident's frames as BLF, each bus a channel."""
    with can.BLFWriter(path) as blf:
        for t, bus, cob, extended, remote, error, dlc, data in frames:
            blf.on_message_received(can.Message(
                timestamp=t, arbitration_id=cob, is_extended_id=extended, is_remote_frame=remote,
                is_error_frame=error, dlc=dlc, data=data, channel=channel_of[bus]))


def _end_helper(helper: subprocess.Popen[bytes]) -> None:
    """Terminate a plot helper, kill it if it does not end within TERMINATE_WAIT_S, and reap it."""
    helper.terminate()
    try:
        helper.wait(timeout=TERMINATE_WAIT_S)
    except subprocess.TimeoutExpired:
        helper.kill()
        helper.wait()


def _enforce_cap(directory: Path, max_bytes: float, keep: str) -> None:
    """Remove the oldest incidents (all files of one stem together) while the directory is over."""
    groups: dict[str, list[Path]] = {}
    for path in directory.iterdir():
        if path.suffix in (".blf", ".mcap", ".json", ".png") and path.is_file():
            groups.setdefault(path.stem, []).append(path)
    total = sum(p.stat().st_size for paths in groups.values() for p in paths)
    for stem in sorted(groups, key=lambda s: min(p.stat().st_mtime for p in groups[s])):
        if total <= max_bytes:
            break
        if stem == keep:
            continue
        for path in groups[stem]:
            total -= path.stat().st_size
            os.remove(path)
        logger.info("flight recorder: removed incident %s (directory over %.0f MB)", stem, max_bytes / 1e6)
