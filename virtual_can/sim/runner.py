"""Runs simulated drives on any python-can bus: the emulator's own, socketcand, or a kernel
``vcan``/``can`` interface. One thread serves every drive on the bus: it receives frames,
hands them to the drives, advances their physics every ``tick_s`` and sends what they say, at
once or, what a drive holds (a SYNC answered late: ``Faults.sync_delay_s``), when it is due (the
thread wakes for it, not at the next tick).

The drives' watch on other nodes (the heartbeat consumer, life guarding) is judged on the bus's
time line, never on when this thread got to look: each frame carries the time it reached the
bus (``Message.timestamp``: the bus server's or the kernel's stamp), and a tick tells the drives
the bus time up to which this thread has seen every frame (:class:`BusClock`). A heartbeat that
reached the bus in time is in time however late it is handled; a host that really went silent is
caught when other frames on the bus (SYNC, other nodes) are stamped past its consumer time, or,
on a silent bus, by the wall clock, but only at a look that followed the previous one closely: a
thread that was held (a starved process, a test's hook) looks at what queued meanwhile first, and
judges nothing for a few looks more, while the bus server's threads, held with it, deliver what
reached their sockets during the hold (with the stamps of its arrival). Where the frames come
through the bus server, the drives are never judged on a bus time past the one up to which every
client's bytes that reached this host are on the bus (the kernel's count of the bytes received on
each connection against its reader's of those it put on the bus; issue 73): a SYNC from the
server's timer, stamped while the host's heartbeat waited in a starved reader, convicts no one.

Owner: the runner thread owns the drives, the bus clock and the hook's calls; other threads reach
the drives through :meth:`DriveSimulator.call`.
"""

from __future__ import annotations

import logging
import math
import queue
import threading
import time
from collections.abc import Callable, Iterable

import can

from can_config.errors import SimError
from can_config.realtime import SIM_PRIORITY, ensure_thread_realtime
from virtual_can.sim.drive import SimulatedDrive

logger = logging.getLogger(__name__)

#: How often the simulated drives' time moves on (their physics runs in sub-steps of 1 ms
#: within it; frames are answered as they arrive). 2 ms rather than 1: half the CPU, which on
#: a two-core machine the driver and the bus server's timer need (SYNC jitter measured 0.7 ms
#: at p99 with 1 ms, 0.04 ms with 2).
DEFAULT_TICK_S = 0.002
#: Frames handled before the drives' time moves on (a bound, so that a flood cannot stop time).
MAX_FRAMES_PER_TICK = 256
#: Two looks at the bus further apart than this: the runner was held in between (starved, or a
#: test's hook), and the frames that queued meanwhile are looked at before the wall clock may
#: convict a silent producer. Many ticks: an ordinary thread on a busy core waits a few ms.
LOOK_GAP_S = 0.05
#: After a look that followed a hold, the bus time the drives are judged on stands still for this
#: many looks (a tick each, each with a wait on the bus): the bus server's threads, held with the
#: runner when the whole process was starved, deliver what reached their sockets meanwhile (a
#: heartbeat stamped in time must not lose the race to a SYNC stamped after it).
SETTLE_LOOKS = 5
#: A frame stamped further than this from the wall clock carries another clock (an interface's
#: own, from its boot): it is taken as stamped when it was handled.
STAMP_TRUST_S = 60.0


class BusClock:
    """The bus's time line as the runner has seen it (``time.time()``'s clock, as the bus stamps).
    Runner thread only.

    ``newest`` is the newest stamp of a frame handled; ``looked`` the wall time before a look that
    emptied the queue and followed the previous look within ``LOOK_GAP_S``: every frame that
    reached the bus by then has been handled. The bus time is the later of the two; after a hold
    the drives are judged on the one before it for ``SETTLE_LOOKS`` looks."""

    def __init__(self) -> None:
        #: Where the bus's frames come from clients whose bytes can wait in a socket or a starved
        #: reader thread (the socketcand server): ``on_bus_until(wall)`` is the bus time up to which
        #: every one of them is on the bus (set by :class:`virtual_can.service.SimService`).
        self.on_bus_until: Callable[[float], float] | None = None
        self.newest = 0.0
        self.looked = 0.0
        self._last_look: float | None = None
        self._settling = 0  # looks left before the bus time the drives are judged on moves again
        #: looks that followed a hold (further than LOOK_GAP_S after the one before): the runner,
        #: and the drives' physics with it, were starved (a test that judges their motion says so)
        self.holds = 0
        self._judged = 0.0  # the bus time they were last judged on

    def stamp(self, msg: can.Message) -> float:
        """The time ``msg`` reached the bus; taken as the bus's newest."""
        wall = time.time()
        stamp = msg.timestamp if abs(msg.timestamp - wall) < STAMP_TRUST_S else wall
        self.newest = max(self.newest, stamp)
        return stamp

    def look(self, wall: float, emptied: bool, on_bus_until: float = math.inf) -> float:
        """A look at the bus begun at ``wall`` (``emptied``: it found the queue empty;
        ``on_bus_until``: the bus time up to which every frame was on the bus at ``wall``); the bus
        time to judge the drives' watch on: never past ``on_bus_until``, so that a SYNC stamped
        after a heartbeat that waits in a starved reader does not convict its producer."""
        steady = self._last_look is not None and wall - self._last_look <= LOOK_GAP_S
        if self._last_look is not None and not steady:
            self.holds += 1
        self._last_look = wall
        if not steady and not self._settling:
            self._settling = SETTLE_LOOKS
        if emptied and steady:
            self.looked = max(self.looked, wall)
        if self._settling:
            self._settling -= 1
            return self._judged
        self._judged = max(self._judged, min(self.now, on_bus_until))
        return self._judged

    @property
    def now(self) -> float:
        return max(self.newest, self.looked)


class DriveSimulator:
    """Simulated drives on one bus. A context manager; ``close()`` is idempotent.

    Fault injection and inspection go through :meth:`call`, which runs a function in the
    simulator thread, so nothing races the drives.

    ``realtime``: the runner thread takes SIM_PRIORITY (below a driver's) where the OS allows it,
    as a simulator standing in for the hardware in a process of its own does. False beside a
    driver of this process that runs at ordinary scheduling: a runner above it would take the
    driver's turn, the reverse of the order the rover has (and a runner that cannot keep up with
    its ticks, as under a VM's emulation, would never leave the core to it).
    """

    def __init__(self, bus: can.BusABC, drives: Iterable[SimulatedDrive], *,
                 tick_s: float = DEFAULT_TICK_S, name: str = "sim", realtime: bool = True) -> None:
        self.bus = bus
        self.realtime = realtime
        self.drives = {d.node_id: d for d in drives}
        self.tick_s = tick_s
        self.errors = 0
        self._calls: queue.SimpleQueue[tuple[Callable[[], object], queue.SimpleQueue[object]]] = (
            queue.SimpleQueue())
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, daemon=True, name=f"virtual_can-{name}")
        self._started = False
        self._name = name
        self._hook: Callable[[str], None] | None = None
        self.clock = BusClock()  # the runner thread's

    def set_hook(self, hook: Callable[[str], None] | None) -> None:
        """Tests only: ``hook(point)`` on the runner thread at its named points: ``"looked"``, right
        after a wait on the bus, before the runner reads its clocks (a hook that holds there stands
        for a starved thread that has not looked at what arrived since)."""
        self._hook = hook

    def _at(self, point: str) -> None:
        hook = self._hook
        if hook is not None:
            hook(point)

    def start(self) -> DriveSimulator:
        if not self._started:
            self._started = True
            self._thread.start()
        return self

    def call(self, fn: Callable[[], object], timeout_s: float = 2.0) -> object:
        """Run ``fn`` in the simulator thread and return its result."""
        if not self._thread.is_alive():
            return fn()
        reply: queue.SimpleQueue[object] = queue.SimpleQueue()
        self._calls.put((fn, reply))
        try:
            result = reply.get(timeout=timeout_s)
        except queue.Empty as err:
            raise SimError("simulator thread did not answer") from err
        if isinstance(result, BaseException):
            raise result
        return result

    def drive(self, node_id: int) -> SimulatedDrive:
        try:
            return self.drives[node_id]
        except KeyError:
            raise SimError(f"no simulated drive with node id {node_id}; have {sorted(self.drives)}") from None

    def _send(self, frames: list[can.Message]) -> None:
        for msg in frames:
            try:
                self.bus.send(msg)
            except can.CanError as err:
                self.errors += 1
                logger.debug("simulator send failed: %s", err)

    def _deliver(self, drives: list[SimulatedDrive], msg: can.Message, now: float) -> None:
        stamp = self.clock.stamp(msg)
        for drive in drives:
            try:
                out = drive.on_frame(msg, now, stamp)
            except Exception:  # a drive must never take the simulator down
                self.errors += 1
                logger.exception("simulated drive %d failed on frame %s", drive.node_id, msg)
                continue
            if out and not drive.faults.tx_dead:
                self._send(out)

    def _release(self, drives: list[SimulatedDrive], now: float) -> None:
        """The frames drives held (a late SYNC answer, and what they made after it) that are due."""
        for drive in drives:
            if drive.next_release is not None and (out := drive.release(now)) and not drive.faults.tx_dead:
                self._send(out)

    def _run_calls(self) -> None:
        """Calls handed to this thread (:meth:`call`), each answered on its own queue."""
        while True:
            try:
                fn, reply = self._calls.get_nowait()
            except queue.Empty:
                return
            try:
                reply.put(fn())
            except Exception as err:
                reply.put(err)

    def _handle_queued(self, drives: list[SimulatedDrive], msg: can.Message | None, now: float) -> bool:
        """``msg`` and every frame already queued behind it, up to MAX_FRAMES_PER_TICK; True if the
        queue was found empty. Nothing is read past the bound (a frame read and not handled would
        be lost: an SDO request among them went unanswered)."""
        for handled in range(1, MAX_FRAMES_PER_TICK + 1):
            if msg is None:
                return True
            if not msg.is_error_frame:
                self._deliver(drives, msg, now)
            if handled == MAX_FRAMES_PER_TICK:
                break
            try:
                msg = self.bus.recv(timeout=0.0)
            except (can.CanError, OSError, ValueError):
                return False
        return False

    def _tick(self, drives: list[SimulatedDrive], now: float, dt: float) -> None:
        """The drives' time moves on, judged against the bus time of a look begun now: what queued
        while this thread was held is handled before any verdict on a silence."""
        wall = time.time()
        on_bus_until = self.clock.on_bus_until(wall) if self.clock.on_bus_until is not None else math.inf
        try:
            first = self.bus.recv(timeout=0.0)
        except (can.CanError, OSError, ValueError):
            first = None
            emptied = False
        else:
            emptied = self._handle_queued(drives, first, now)
        bus_now = self.clock.look(wall, emptied, on_bus_until)
        for drive in drives:
            try:
                out = drive.tick(now, dt, bus_now)
            except Exception:
                self.errors += 1
                logger.exception("simulated drive %d failed in tick", drive.node_id)
                continue
            if out and not drive.faults.tx_dead:
                self._send(out)

    def _run(self) -> None:
        if self.realtime:
            ensure_thread_realtime(f"simulated drives on {self._name}", SIM_PRIORITY)
        drives = list(self.drives.values())
        tick = self.tick_s
        last = time.monotonic()
        next_tick = last + tick
        while not self._stop.is_set():
            now = time.monotonic()
            wake = min((t for d in drives if (t := d.next_release) is not None), default=next_tick)
            try:
                msg = self.bus.recv(timeout=max(0.0, min(next_tick, wake) - now))
            except (can.CanError, OSError, ValueError) as err:
                if self._stop.is_set():
                    break
                self.errors += 1
                logger.warning("simulator bus receive failed (%s); retrying", err)
                time.sleep(0.05)
                continue
            self._at("looked")
            now = time.monotonic()
            self._handle_queued(drives, msg, now)
            self._release(drives, now)
            self._run_calls()
            if now >= next_tick:
                dt = min(now - last, 10 * tick)
                last = now
                next_tick += tick
                if next_tick < now:
                    next_tick = now + tick
                self._tick(drives, now, dt)

    def close(self) -> None:
        self._stop.set()
        if self._thread.is_alive() and self._thread is not threading.current_thread():
            self._thread.join(timeout=2.0)

    def __enter__(self) -> DriveSimulator:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.close()
