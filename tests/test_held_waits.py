"""A hold of the whole process (a crowded machine, a VM's emulation) is not a drive's silence.

On a crowded CI run the kernel tier's test process was held 3.5 s while an SDO write waited on
its 2 s timeout: the answer sat in the socket's buffer, unread by the held receive thread, and the
waiter, woken past its deadline, blamed the drive. Waits for an answer (the SDO client's, the
state cache's) do not count such a hold (motor_driver.process.held), and a drive that never
answers is still declared silent. The hooks below hold the waiting thread inside its wait and
let the answer come only once the waiter runs again, as a held receive thread does; the waits
before the fix (a plain deadline) fail every one of them.
"""

from __future__ import annotations

import queue
import socket
import threading
import time
from collections.abc import Callable, Iterator
from typing import Any

import can
import canopen
import pytest
from hypothesis import given
from hypothesis import strategies as st

from can_config import RoverConfig
from can_config.eds import load_drive_od
from can_config.errors import SdoTimeoutError
from can_config.model import GENERIC_EDS
from motor_driver import MotorDriver
from motor_driver.bus import cyclic
from motor_driver.bus.sdo_client import MultiplexedSdoClient, OwnAnswersNode
from motor_driver.drive.constants import SDO_TRANSFER_TIMEOUTS
from motor_driver.drive.sdo import SdoPort
from motor_driver.process.held import HELD_GAP_S, MAX_RESUMES, POLL_S, RESUME_S, HeldDeadline
from virtual_can import SimService

from .conftest import make_config

NODE = 5
TIMEOUT_S = 2.0
HOLD_S = TIMEOUT_S + 0.5  # longer than the whole timeout, as the CI run's 3.5 s hold was
DEVICE_TYPE = 0x00020192


class Responder:
    """Node 5's SDO server for one object (0x1000), on its own python-can bus: it answers a
    request only once released, from the releasing thread at once when the request is there (the
    answer reaches the waiter when its process runs again)."""

    def __init__(self, channel: str) -> None:
        self.bus = can.Bus(interface="virtual", channel=channel)
        self.requests = 0
        self._lock = threading.Lock()
        self._released = False
        self._pending = False
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="responder", daemon=True)
        self._thread.start()

    def release(self) -> None:
        with self._lock:
            self._released = True
            self._answer_if_due()

    def _answer_if_due(self) -> None:
        if self._pending and self._released:
            answer = bytes([0x43, 0x00, 0x10, 0x00]) + DEVICE_TYPE.to_bytes(4, "little")
            self.bus.send(can.Message(arbitration_id=0x580 + NODE, data=answer, is_extended_id=False))
            self._pending = False

    def _run(self) -> None:
        while not self._stop.is_set():
            msg = self.bus.recv(POLL_S)
            if msg is not None and msg.arbitration_id == 0x600 + NODE and msg.data[0] == 0x40:
                with self._lock:
                    self.requests += 1
                    self._pending = True
                    self._answer_if_due()

    def close(self) -> None:
        self._stop.set()
        self._thread.join(30.0)
        self.bus.shutdown()


def hold_past(until: float) -> None:
    """The calling thread held, looking at nothing, until the clock is past ``until`` (past the
    wait's deadline: the hold the test injects, not a wait for a condition)."""
    while time.monotonic() < until:
        time.sleep(POLL_S)


class HeldQueue(queue.Queue):  # type: ignore[type-arg]
    """The SDO client's answer queue, with a hook inside its wait: the first wait is held
    ``HOLD_S`` (the whole process held), and each wait after it calls ``after_hold``."""

    def __init__(self, after_hold: Callable[[], None]) -> None:
        super().__init__()
        self.waits = 0
        self._after_hold = after_hold

    def get(self, block: bool = True, timeout: float | None = None) -> bytes:
        self.waits += 1
        if self.waits == 1:
            hold_past(time.monotonic() + HOLD_S)  # held: nothing delivered meanwhile
        else:
            self._after_hold()
        answer: bytes = super().get(block, timeout)
        return answer


@pytest.fixture
def sdo(request: pytest.FixtureRequest) -> Iterator[tuple[SdoPort, MultiplexedSdoClient, Responder]]:
    channel = f"held-{request.node.name}"
    responder = Responder(channel)
    network = canopen.Network(can.Bus(interface="virtual", channel=channel))
    network.connect()
    node = OwnAnswersNode(NODE, load_drive_od(GENERIC_EDS, NODE))
    network.add_node(node)
    port = SdoPort("held", node, node.object_dictionary, getattr(request, "param", TIMEOUT_S))
    try:
        yield port, node.sdo, responder
    finally:
        network.disconnect()
        responder.close()


def test_an_sdo_answer_that_comes_after_the_process_was_held_past_the_timeout_is_taken(
        sdo: tuple[SdoPort, MultiplexedSdoClient, Responder]) -> None:
    port, client, responder = sdo
    client.responses = HeldQueue(after_hold=responder.release)
    assert port.read_value(0x1000) == DEVICE_TYPE
    assert responder.requests == 1  # answered, not asked again
    assert client.responses.waits > 1


@pytest.mark.parametrize("sdo", [0.5], indirect=True)  # the port's SDO timeout
def test_a_transfer_held_past_its_whole_bound_is_not_aborted_for_the_hold(
        sdo: tuple[SdoPort, MultiplexedSdoClient, Responder]) -> None:
    """The whole transfer's bound (SDO_TRANSFER_TIMEOUTS x the SDO timeout) is a held deadline
    too: the hold here is longer than the whole bound of a port with a 0.5 s timeout, and the
    answer, there once the process runs again, is taken (a plain deadline aborted the transfer)."""
    port, client, responder = sdo
    assert HOLD_S > SDO_TRANSFER_TIMEOUTS * 0.5
    client.responses = HeldQueue(after_hold=responder.release)
    assert port.read_value(0x1000) == DEVICE_TYPE
    assert responder.requests == 1


def test_a_drive_that_never_answers_is_still_silent_and_the_hold_is_said(
        sdo: tuple[SdoPort, MultiplexedSdoClient, Responder]) -> None:
    port, client, responder = sdo
    client.responses = HeldQueue(after_hold=lambda: None)  # never released
    with pytest.raises(SdoTimeoutError, match=r"got no answer.*held up to 2\.\d s meanwhile; looked again after it\)"):
        port.read_value(0x1000)
    assert responder.requests == 1


def test_a_state_wait_held_past_its_timeout_sees_what_came_meanwhile(
        driver_factory: Callable[[RoverConfig], tuple[SimService, MotorDriver]]) -> None:
    _, driver = driver_factory(make_config(1))
    cache = driver.drive("joint1").cache
    looks = [0]

    def done() -> bool:  # the hook inside the wait: its second look is held past the timeout
        looks[0] += 1
        if looks[0] == 2:
            hold_past(time.monotonic() + HOLD_S)
        return looks[0] >= 3  # the statusword the held receive thread hands over once it runs

    assert cache.wait_until(done, TIMEOUT_S)
    never = [0]

    def silent() -> bool:
        never[0] += 1
        if never[0] == 2:
            hold_past(time.monotonic() + HOLD_S)
        return False

    assert not cache.wait_until(silent, 0.2)  # a drive that never answers still times out


class FakeClock:
    def __init__(self) -> None:
        self.now = 0.0

    def __call__(self) -> float:
        return self.now


def reference_left(timeout: float, looks: list[tuple[float, float]]) -> list[float]:
    """The rule, written down on its own: at each look (its time from the start, the gap before
    it), a gap over HELD_GAP_S that left less than a look (min(RESUME_S, timeout)) of the wait
    gives one look from its end, MAX_RESUMES at most; what is left at each look."""
    deadline, resumes, out = timeout, 0, []
    look = min(RESUME_S, timeout)
    for at, gap in looks:
        if gap > HELD_GAP_S and at + look > deadline and resumes < MAX_RESUMES:
            resumes += 1
            deadline = at + look
        out.append(deadline - at)
    return out


@given(timeout=st.floats(0.05, 10.0), gaps=st.lists(st.floats(0.0, 8.0), min_size=1, max_size=400))
def test_a_deadline_looks_again_after_a_hold_and_never_waits_unbounded(timeout: float, gaps: list[float]) -> None:
    clock = FakeClock()
    deadline = HeldDeadline(timeout, clock)
    looks: list[tuple[float, float]] = []
    lefts: list[float] = []
    for gap in gaps:
        clock.now += gap
        lefts.append(deadline.remaining())
        looks.append((clock.now, gap))
    assert lefts == pytest.approx(reference_left(timeout, looks), abs=1e-9)
    resume = min(RESUME_S, timeout)
    longest = max(gaps)
    resumes = 0
    for (at, gap), left in zip(looks, lefts, strict=True):
        assert left <= max(timeout - at, resume) + 1e-9  # never more than the timeout, or one look
        if gap > HELD_GAP_S and resumes < MAX_RESUMES:  # a hold, looks left: at least one look after it
            assert left >= resume - 1e-9
            resumes += left - resume < 1e-9
        if left > 0:  # still waiting: within the timeout and the looks after holds
            assert at < timeout + MAX_RESUMES * (resume + longest) + 1e-9
        if not any(g > HELD_GAP_S for _, g in looks[:looks.index((at, gap)) + 1]):
            assert (left > 0) == (at < timeout) or abs(at - timeout) < 1e-9  # no hold: a plain timeout


class SplitGreeting:
    """A socketcand daemon on 127.0.0.1 that says half its greeting, the rest once told (while
    the client is held), then answers ``< open ... >`` with ``< ok >``."""

    def __init__(self) -> None:
        self.listener = socket.create_server(("127.0.0.1", 0))
        self.port = self.listener.getsockname()[1]
        self.rest = threading.Event()
        self._thread = threading.Thread(target=self._serve, name="split-greeting", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        conn, _ = self.listener.accept()
        with conn:
            try:
                conn.sendall(b"< h")
                self.rest.wait(60.0)
                conn.sendall(b"i >")
                while data := conn.recv(256):
                    if b"< open" in data:
                        conn.sendall(b"< ok >")
            except OSError:
                pass  # the client gave up: its error is the test's

    def close(self) -> None:
        self.listener.close()
        self._thread.join(30.0)


class HeldSocket:
    """The cyclic job's connection, with a hook in its first read: it returns what came, then the
    daemon says the rest and the thread is held past the wait's deadline before it looks again."""

    def __init__(self, sock: socket.socket, daemon: SplitGreeting, timeout_s: float) -> None:
        self._sock, self._daemon, self._timeout_s = sock, daemon, timeout_s
        self.reads = 0

    def recv(self, size: int, *flags: int) -> bytes:
        self.reads += 1
        chunk = self._sock.recv(size, *flags)
        if self.reads == 1:
            self._daemon.rest.set()
            hold_past(time.monotonic() + self._timeout_s + 0.5)
        return chunk

    def __getattr__(self, name: str) -> Any:
        return getattr(self._sock, name)


def test_a_daemons_reply_that_came_while_the_process_was_held_is_read(monkeypatch: pytest.MonkeyPatch) -> None:
    """The socketcand daemon's greeting to a cyclic job, its end in the buffer while the job's
    thread was held past its reply timeout: read, not a 'bus lost' (a plain deadline raised
    before reading the buffer again)."""
    daemon = SplitGreeting()
    timeout_s = 0.5
    held: list[HeldSocket] = []
    connect = socket.create_connection

    def held_connection(*args: Any, **kwargs: Any) -> Any:
        held.append(HeldSocket(connect(*args, **kwargs), daemon, timeout_s))
        return held[-1]

    monkeypatch.setattr(cyclic.socket, "create_connection", held_connection)
    try:
        task = cyclic.DaemonCyclicTask("127.0.0.1", daemon.port, "can0",
                                       can.Message(arbitration_id=0x80, data=b"", is_extended_id=False), 0.01,
                                       timeout_s=timeout_s)
        task.stop()
    finally:
        daemon.close()
    assert held and held[0].reads >= 2
