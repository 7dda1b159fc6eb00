"""A socketcand server that stops reading (hung or stopped, blocked on its own CAN writes with no
node acknowledging, a dropped link): once the connection's buffers are full, a write blocks. It
blocked for ever, holding the bus's send lock: another thread's stop waited behind it, and so did
the supervisor's host heartbeat, for every bus, with nothing said (an independent review's
finding). Now a write blocks at most SEND_STALL_S, then the connection is given up and the cause
said; the heartbeat never waits on one bus; the supervisor counts the bus lost, naming the stall.

The server here is real TCP on 127.0.0.1 (the socketcand handshake, then no read at all, its
receive buffer made small so the connection fills quickly); the bus is opened as the driver opens
it (``open_bus``). Each wait is bounded only to fail instead of hanging: nothing is timed."""

from __future__ import annotations

import logging
import socket
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from can_config import load_config
from motor_driver.bus.adapters import SendStalled, bound_sends, stall_of
from motor_driver.bus.connect import open_bus
from motor_driver.bus.handle import BusHandle
from motor_driver.drive.ledger import BusRecord
from motor_driver.process.ratelimit import RateLimitedLog
from motor_driver.runtime.supervise_bus import BusSupervision

#: Only for a wait to fail instead of hanging the suite (the stall itself is SEND_STALL_S).
BOUND_S = 60.0
RPDO = (0x201, b"\x0f\x00\x10\x27\x00\x00\x00\x00")


class DeafServer:
    """A socketcand daemon that answers the handshake and then never reads again."""

    def __init__(self) -> None:
        self.listener = socket.socket()
        self.listener.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # inherited by the connection
        self.listener.bind(("127.0.0.1", 0))
        self.listener.listen(1)
        self.port = self.listener.getsockname()[1]
        self.conn: socket.socket | None = None
        self._thread = threading.Thread(target=self._serve, name="deaf-server", daemon=True)
        self._thread.start()

    def _serve(self) -> None:
        while self.conn is None:  # the driver's probe of the port (wait_for_server) comes first
            conn, _ = self.listener.accept()
            try:
                conn.sendall(b"< hi >")
                if not conn.recv(256):  # < open can0 >
                    conn.close()
                    continue
                conn.sendall(b"< ok >")
                conn.recv(256)  # < rawmode >
                conn.sendall(b"< ok >")
            except OSError:
                conn.close()
                continue
            self.conn = conn

    def rest_until_end(self) -> bytes:
        """Everything the client wrote, read now, up to the end of its stream."""
        assert self.conn is not None
        self.conn.settimeout(BOUND_S)
        chunks = []
        while chunk := self.conn.recv(65536):
            chunks.append(chunk)
        return b"".join(chunks)

    def close(self) -> None:
        if self.conn is not None:
            self.conn.close()
        self.listener.close()


@pytest.fixture
def deaf() -> Iterator[tuple[DeafServer, BusHandle]]:
    server = DeafServer()
    bus = open_bus({"interface": "socketcand", "channel": "can0", "host": "127.0.0.1", "port": server.port})
    handle = BusHandle("can0", bus, owned=True, sync_period_s=0.0)
    try:
        yield server, handle
    finally:
        handle.close()
        server.close()


def stream_until_refused(handle: BusHandle) -> BaseException:
    """Set-points written as fast as they go, on a thread, until one is refused: that error."""
    refused: list[BaseException] = []
    done = threading.Event()

    def stream() -> None:
        try:
            while True:
                handle.network.send_message(*RPDO)
        except Exception as err:
            refused.append(err)
        finally:
            done.set()

    threading.Thread(target=stream, name="streamer", daemon=True).start()
    assert done.wait(BOUND_S), "a write to a server that stopped reading never came back (the send lock held with it)"
    return refused[0]


def test_a_write_to_a_server_that_stopped_reading_gives_the_connection_up_and_says_why(
        deaf: tuple[DeafServer, BusHandle]) -> None:
    server, handle = deaf
    err = stream_until_refused(handle)
    assert isinstance(err, SendStalled) and "stopped reading" in str(err), repr(err)
    assert stall_of(handle.bus) == str(err)
    # every later write (another thread's stop) is refused at once, naming the same cause
    with pytest.raises(SendStalled, match="stopped reading"):
        handle.network.send_message(0x000, b"\x02\x00")
    # the connection's write side was shut: the server reads to the end of the stream (kept open,
    # this read would wait for ever), and every frame's text in it is whole but the last, which no
    # later write completed with the text of another
    parts = server.rest_until_end().split(b">")
    assert all(part.strip().startswith(b"<") and part.count(b"<") == 1 for part in parts[:-1] if part.strip())
    assert parts[-1].count(b"<") <= 1


def test_the_bus_own_send_gives_the_connection_up_inside_its_callers_lock(deaf: tuple[DeafServer, BusHandle]) -> None:
    """python-can's own send (the SYNC thread's, the heartbeat's) under the send lock, as its
    callers hold it: the stall is recorded and the write side shut before the lock is let go, so
    no writer waiting for the lock adds to the frame cut in two (an independent review's finding:
    the SYNC thread's error handler ran after its lock was released)."""
    _, handle = deaf
    sync = can.Message(arbitration_id=0x080, data=b"", is_extended_id=False)
    with handle.network.send_lock:
        with pytest.raises(SendStalled, match="stopped reading"):
            while True:
                handle.bus.send(sync)
        assert "stopped reading" in stall_of(handle.bus)  # given up while the lock is still held


def test_a_heartbeat_not_sent_is_tried_again_the_next_period(deaf: tuple[DeafServer, BusHandle], tmp_path: Path) -> None:
    """A beat skipped (the send lock held a moment) moved the next one a whole heartbeat period
    on: the drive went two periods without one, and nothing said so. It is tried again at the
    supervisor's next period. The supervisor's clock is its argument here: nothing is timed."""
    server, handle = deaf
    config_file = tmp_path / "rover.yaml"
    config_file.write_text("buses: [{name: can0, interface: socketcand, channel: can0,"
                           f" kwargs: {{host: 127.0.0.1, port: {server.port}}}}}]\n"
                           "drives: [{name: a, node_id: 1, counts_per_rev: 4096}]\n")
    config = load_config(config_file)
    watch = BusSupervision(config, {"can0": handle}, None, RateLimitedLog(logging.getLogger(__name__)),
                           {}, {}, lambda drive: None, lambda event: None)
    record = watch.bus_records["can0"]
    watch.beat(1000.0)
    watch.beat(1000.01)  # from here on a beat every heartbeat period
    t = record.next_beat
    assert handle.host_beats == 2 and t == pytest.approx(1000.0 + config.buses[0].host_heartbeat_s)
    with handle.network.send_lock:  # held a moment longer than the beat waits
        watch.beat(t)
    assert handle.host_beats == 2 and record.send_failing is not None
    watch.beat(t + 0.01)  # the supervisor's next period
    assert handle.host_beats == 3 and record.send_failing is None


def test_the_host_heartbeat_never_waits_on_the_bus(deaf: tuple[DeafServer, BusHandle]) -> None:
    _, handle = deaf
    said: list[str | None] = []

    def beat_on_a_thread() -> str | None:
        said.clear()
        done = threading.Event()
        threading.Thread(target=lambda: (said.append(handle.beat(127)), done.set()), daemon=True).start()
        assert done.wait(BOUND_S), "the host heartbeat waited on the bus (the supervisor's loop with it)"
        return said[0]

    assert beat_on_a_thread() is None  # a listener shown to listen: the beat goes out while the server has room
    beats = handle.host_beats
    with handle.network.send_lock:  # a writer holding the lock (blocked in its write, or starved)
        why = beat_on_a_thread()
    assert why is not None and "send lock" in why, why
    sock = handle.bus._SocketCanDaemonBus__socket  # type: ignore[attr-defined]
    with handle.network.send_lock:  # the connection filled by a writer, its write not yet timed out
        while True:
            try:
                sock.send(b"< send 201 1 00 >", socket.MSG_DONTWAIT)
            except BlockingIOError:
                break
    why = beat_on_a_thread()
    assert why is not None and "not reading" in why, why
    assert handle.host_beats == beats


def test_the_supervisor_counts_the_bus_lost_naming_the_stall(
        deaf: tuple[DeafServer, BusHandle], tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    server, handle = deaf
    config_file = tmp_path / "rover.yaml"
    config_file.write_text("buses: [{name: can0, interface: socketcand, channel: can0,"
                           f" kwargs: {{host: 127.0.0.1, port: {server.port}}}}}]\n"
                           "drives: [{name: a, node_id: 1, counts_per_rev: 4096}]\n")
    handle.owned = False  # nothing reconnected here: the verdict is what is looked at
    gone: list[str] = []
    watch = BusSupervision(load_config(config_file), {"can0": handle}, None, RateLimitedLog(logging.getLogger(__name__)),
                           {}, {}, lambda drive: gone.append(drive.name), lambda event: None)
    watch.supervise_buses(time.monotonic())
    assert not watch.bus_records["can0"].lost  # shown to look: a bus whose server still reads is not lost
    stream_until_refused(handle)
    with caplog.at_level(logging.ERROR, logger="motor_driver.runtime.supervise_bus"):
        watch.supervise_buses(time.monotonic())
    record: BusRecord = watch.bus_records["can0"]
    assert record.lost
    assert any("bus can0 lost (a write to the socketcand server blocked" in line for line in caplog.messages), \
        caplog.messages


def test_a_bus_that_is_not_socketcand_has_no_stall() -> None:
    """A virtual bus's send is left as it is; a timed-out write's error from elsewhere gives nothing up."""
    bus = can.Bus(interface="virtual", channel="stall-none", receive_own_messages=False)
    try:
        send = bus.send
        assert bound_sends(bus).send == send
        assert stall_of(bus, BlockingIOError(11, "Resource temporarily unavailable")) == ""
    finally:
        bus.shutdown()
