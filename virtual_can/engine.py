"""The emulator's bus engine: named channels that carry frames between endpoints.

One engine serves both the in-process python-can bus (:mod:`virtual_can.bus`) and the
socketcand server (:mod:`virtual_can.server`). A frame sent on a channel is delivered, in
order, to every other endpoint attached to that channel. Optional per channel:

* wire-time mode: frames wait for the bus to be free, take their real bit time at the
  configured bitrate, and contend by identifier (lowest id wins), so a flooded channel
  carries no more frames than a real bus. The wire keeps its own time: a frame sent onto an
  idle wire starts when it was sent, and the frames sent while another is on the wire
  contend when it ends, however late the wire thread gets to run;
* fault injection: drop, delay or corrupt frames with a given probability.

A frame may also be scheduled ahead with its bus time (:meth:`Channel.schedule`: the broadcast
manager's cyclic frames, as a controller with a timed transmission queues them): it goes on the
channel before any frame stamped at or after that time, and at that time at the latest.
"""

from __future__ import annotations

import collections
import heapq
import itertools
import logging
import random
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import can

from virtual_can.wire import frame_time_s

logger = logging.getLogger(__name__)

Deliver = Callable[[can.Message], None]

#: How long the wire-time thread waits for work before checking for shutdown.
WIRE_IDLE_WAIT_S = 0.05


@dataclass
class FaultSettings:
    """Probabilities (0..1) of frame faults on one channel."""

    drop: float = 0.0
    delay: float = 0.0
    delay_s: float = 0.005
    corrupt: float = 0.0

    def any(self) -> bool:
        return self.drop > 0 or self.delay > 0 or self.corrupt > 0


@dataclass
class ChannelStats:
    frames: int = 0
    dropped: int = 0
    delayed: int = 0
    corrupted: int = 0
    busy_s: float = 0.0  # wire time used (wire-time mode)
    started: float = field(default_factory=time.monotonic)


class Endpoint:
    """One attachment to a channel: something frames are delivered to."""

    def __init__(self, channel: Channel, deliver: Deliver, name: str) -> None:
        self.channel = channel
        self.deliver = deliver
        self.name = name

    def send(self, msg: can.Message) -> None:
        self.channel.send(msg, self)

    def detach(self) -> None:
        self.channel.detach(self)


class Channel:
    """One named CAN channel (e.g. ``can0``)."""

    def __init__(self, name: str, bitrate: int = 1_000_000, wire_time: bool = False,
                 seed: int | None = None) -> None:
        self.name = name
        self.bitrate = bitrate
        self.stats = ChannelStats()
        self.faults = FaultSettings()
        self._endpoints: tuple[Endpoint, ...] = ()
        self._lock = threading.Lock()
        self._rng = random.Random(seed)
        self._wire_time = wire_time
        # wire-time mode: frames in the order sent (with the time sent), and the ones that have
        # reached the wire and contend for it, by identifier
        self._sent: collections.deque[tuple[float, can.Message, Endpoint | None]] = collections.deque()
        self._contending: list[tuple[int, int, can.Message, Endpoint | None]] = []
        self._seq = itertools.count()
        self._wire_cv = threading.Condition()
        self._closed = False
        self._wire_thread: threading.Thread | None = None
        self._timers: set[threading.Timer] = set()
        self._last_stamp = 0.0  # of the newest frame delivered; guarded by _lock
        self._scheduled: list[tuple[float, int, can.Message]] = []  # (bus time, seq, frame); guarded by _lock
        if wire_time:
            self._wire_thread = threading.Thread(target=self._wire_loop, daemon=True,
                                                 name=f"virtual_can-wire-{name}")
            self._wire_thread.start()

    # -- endpoints
    def attach(self, deliver: Deliver, name: str = "endpoint") -> Endpoint:
        endpoint = Endpoint(self, deliver, name)
        with self._lock:
            self._endpoints = (*self._endpoints, endpoint)
        return endpoint

    def detach(self, endpoint: Endpoint) -> None:
        with self._lock:
            self._endpoints = tuple(e for e in self._endpoints if e is not endpoint)

    # -- sending
    def send(self, msg: can.Message, sender: Endpoint | None = None) -> None:
        """Put a frame on the channel; every endpoint but ``sender`` receives it."""
        if self._closed:
            raise can.CanOperationError(f"channel {self.name} is closed")
        if self.faults.any():
            msg_or_none = self._inject(msg, sender)
            if msg_or_none is None:
                return
            msg = msg_or_none
        if self._wire_time:
            with self._wire_cv:
                self._sent.append((time.perf_counter(), msg, sender))
                self._wire_cv.notify()
            return
        self._deliver(msg, sender)

    def schedule(self, msg: can.Message) -> None:
        """A frame whose bus time (``msg.timestamp``, ``time.time()``'s clock) is known ahead: it
        is delivered before any frame stamped at or after it, or by :meth:`flush_scheduled` once
        that time has come, whichever is first. In wire-time mode it is sent then instead (it
        contends for the wire like any frame)."""
        if self._closed:
            raise can.CanOperationError(f"channel {self.name} is closed")
        with self._lock:
            heapq.heappush(self._scheduled, (msg.timestamp, next(self._seq), msg))

    def flush_scheduled(self, now: float) -> None:
        """Deliver the scheduled frames whose bus time is ``now`` (``time.time()``) or earlier."""
        due: list[can.Message] = []
        with self._lock:
            while self._scheduled and self._scheduled[0][0] <= now:
                due.append(heapq.heappop(self._scheduled)[2])
            if not self._wire_time:
                for msg in due:
                    self._deliver_locked(msg, None)
                return
        for msg in due:  # wire-time mode: onto the wire now, where it contends
            msg.timestamp = 0.0
            self.send(msg)

    def _deliver(self, msg: can.Message, sender: Endpoint | None) -> None:
        with self._lock:  # one frame at a time: every endpoint sees the same order
            # stamped when it reached the bus (a server's reader gives the kernel's arrival time)
            # or now; never before the frame delivered before it: one wire, one order in time
            stamp = msg.timestamp or time.time()
            while self._scheduled and self._scheduled[0][0] <= stamp and not self._wire_time:
                self._deliver_locked(heapq.heappop(self._scheduled)[2], None)  # its bus time came first
            msg.timestamp = stamp
            self._deliver_locked(msg, sender)

    def _deliver_locked(self, msg: can.Message, sender: Endpoint | None) -> None:
        self.stats.frames += 1
        msg.timestamp = self._last_stamp = max(msg.timestamp, self._last_stamp)
        for endpoint in self._endpoints:
            if endpoint is not sender:
                endpoint.deliver(msg)

    def _inject(self, msg: can.Message, sender: Endpoint | None) -> can.Message | None:
        faults = self.faults
        rng = self._rng
        if faults.drop and rng.random() < faults.drop:
            self.stats.dropped += 1
            return None
        if faults.corrupt and msg.dlc and rng.random() < faults.corrupt:
            data = bytearray(msg.data)
            pos = rng.randrange(len(data))
            data[pos] ^= 1 << rng.randrange(8)
            self.stats.corrupted += 1
            msg = can.Message(arbitration_id=msg.arbitration_id, data=bytes(data),
                              is_extended_id=msg.is_extended_id, timestamp=msg.timestamp)
        if faults.delay and rng.random() < faults.delay:
            self.stats.delayed += 1
            timer = threading.Timer(faults.delay_s, self._delayed, (msg, sender))
            timer.daemon = True
            with self._lock:
                self._timers.add(timer)
            timer.start()
            return None
        return msg

    def _delayed(self, msg: can.Message, sender: Endpoint | None) -> None:
        with self._lock:
            self._timers = {t for t in self._timers if t.is_alive() and t is not threading.current_thread()}
        if not self._closed:
            msg.timestamp = 0.0  # it reaches the wire now, not when it reached the server
            self._deliver(msg, sender)

    # -- wire time
    def _wire_loop(self) -> None:
        free_at = time.perf_counter()  # when the wire is free, in perf_counter time
        wall_offset = time.time() - free_at  # frames are stamped at their end of frame, as a controller does
        sent, contending = self._sent, self._contending
        while True:
            with self._wire_cv:
                while not sent and not contending and not self._closed:
                    self._wire_cv.wait(WIRE_IDLE_WAIT_S)
                if self._closed:
                    return
                # the next transmission starts when the wire is free, or when the first waiting
                # frame was sent onto an idle wire; every frame sent by then contends
                start = free_at if contending else max(free_at, sent[0][0])
                while sent and sent[0][0] <= start:
                    _, queued, queued_by = sent.popleft()
                    heapq.heappush(contending, (queued.arbitration_id, next(self._seq), queued, queued_by))
                _, _, msg, sender = heapq.heappop(contending)
            duration = frame_time_s(msg.dlc, self.bitrate, extended=msg.is_extended_id)
            free_at = start + duration
            delay = free_at - time.perf_counter()
            if delay > 0.0002:
                time.sleep(delay - 0.0001)
            while time.perf_counter() < free_at:
                pass
            self.stats.busy_s += duration
            msg.timestamp = free_at + wall_offset
            self._deliver(msg, sender)

    def load(self) -> float:
        """Fraction of wall time the wire was busy since the stats were reset (wire-time mode)."""
        elapsed = time.monotonic() - self.stats.started
        return self.stats.busy_s / elapsed if elapsed > 0 else 0.0

    def reset_stats(self) -> None:
        self.stats = ChannelStats()

    def close(self) -> None:
        self._closed = True
        with self._wire_cv:
            self._wire_cv.notify_all()
        if self._wire_thread is not None:
            self._wire_thread.join(timeout=1.0)
        with self._lock:
            timers, self._timers = self._timers, set()
        for timer in timers:
            timer.cancel()


class BusEngine:
    """A set of named channels. A context manager; ``close()`` is idempotent."""

    def __init__(self, *, bitrate: int = 1_000_000, wire_time: bool = False,
                 seed: int | None = None) -> None:
        self.bitrate = bitrate
        self.wire_time = wire_time
        self._seed = seed
        self._channels: dict[str, Channel] = {}
        self._lock = threading.Lock()

    def channel(self, name: str) -> Channel:
        """The channel called ``name``, created on first use."""
        with self._lock:
            chan = self._channels.get(name)
            if chan is None:
                chan = Channel(name, self.bitrate, self.wire_time, self._seed)
                self._channels[name] = chan
            return chan

    @property
    def channels(self) -> dict[str, Channel]:
        return dict(self._channels)

    def close(self) -> None:
        with self._lock:
            channels, self._channels = list(self._channels.values()), {}
        for chan in channels:
            chan.close()

    def __enter__(self) -> BusEngine:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()
