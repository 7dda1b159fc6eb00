"""Pins the dependency internals motor_driver/bus/adapters.py relies on, against the installed
python-can and canopen: an upgrade that changes them fails here, not on the rover."""

from __future__ import annotations

import errno
import inspect
import socket
import threading
import time
from collections.abc import Iterator

import can
import canopen
import pytest
from can.interfaces.socketcand.socketcand import (
    SocketCanDaemonBus,
    convert_ascii_message_to_can_message,
    convert_can_message_to_ascii_message,
)
from hypothesis import given
from hypothesis import strategies as st

from motor_driver.bus.adapters import (
    CLOSED_PAUSE_S,
    SOCKETCAND_SOCKET_ATTRIBUTE,
    SOCKETCAND_TCP_TUNE,
    SYNC_TEXT_BYTES,
    GuardedNetwork,
    HeldFramesLost,
    connection_closed,
    hold_lone_sync,
    parse_frames,
    queue_full,
    socketcand_sender,
)
from motor_driver.bus.connect import open_bus
from virtual_can import SimService
from virtual_can.client import format_frame

from .conftest import on_the_bus, received_id, wait_for


def test_the_socketcand_client_keeps_its_socket_where_connection_closed_looks() -> None:
    sim = SimService([], port=0)
    bus = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
    try:
        assert isinstance(getattr(bus, SOCKETCAND_SOCKET_ATTRIBUTE), socket.socket)
        assert not connection_closed(bus)
        sim.close()  # the server goes away: python-can's recv() only ever returns None ...
        deadline = time.monotonic() + 2.0
        while not connection_closed(bus):  # ... the peek tells
            assert time.monotonic() < deadline, "connection_closed() never saw the server go"
            time.sleep(0.01)
        assert bus.recv(0.05) is None
    finally:
        bus.shutdown()
        sim.close()
    assert not connection_closed(can.Bus(interface="virtual", channel="pin"))  # other interfaces: False


def test_a_socketcand_bus_whose_server_went_pauses_its_reads_instead_of_spinning() -> None:
    """python-can reads a lost server's end of stream as 'no frame' at once: recv() went round
    thousands of times until its timeout, and a real-time receive thread with it. Opened as the
    driver opens it, the bus pauses CLOSED_PAUSE_S after each such read: at most a read per pause
    (the count is bounded by the sleeps, not by how fast the machine is)."""
    sim = SimService([], port=0)
    bus = open_bus({"interface": "socketcand", "channel": "can0", "host": sim.host, "port": sim.port})
    reads = 0
    inner = bus._recv_internal

    def counted(timeout: float | None) -> tuple[can.Message | None, bool]:
        nonlocal reads
        reads += 1
        return inner(timeout)  # type: ignore[no-any-return]

    try:
        sim.close()
        wait_for(lambda: connection_closed(bus), 10.0, "the server gone")
        bus._recv_internal = counted  # type: ignore[method-assign]
        assert bus.recv(0.3) is None
        assert reads <= 0.3 / CLOSED_PAUSE_S + 2, reads
    finally:
        bus.shutdown()
        sim.close()


def test_canopen_notify_is_what_guarded_network_overrides() -> None:
    params = list(inspect.signature(canopen.Network.notify).parameters)
    assert params == ["self", "can_id", "data", "timestamp"], params
    network = canopen.Network()
    assert isinstance(network.subscribers, dict) and hasattr(network.scanner, "on_message_received")
    source = inspect.getsource(canopen.Network.notify)
    assert "self.subscribers" in source and "self.scanner.on_message_received" in source, source


def test_guarded_network_survives_a_raising_callback() -> None:
    network = GuardedNetwork()
    seen: list[int] = []

    def broken(can_id: int, data: bytearray, timestamp: float) -> None:
        raise ValueError("malformed")

    network.subscribe(0x181, broken)
    network.subscribe(0x181, lambda can_id, data, ts: seen.append(can_id))
    network.notify(0x181, bytearray(b"\x01"), 0.0)
    assert seen == [0x181] and network.rejected_frames == 1
    with pytest.raises(ValueError):
        canopen.Network.notify(_plain(broken), 0x181, bytearray(b"\x01"), 0.0)  # canopen's own would raise


def _plain(callback: object) -> canopen.Network:
    network = canopen.Network()
    network.subscribe(0x181, callback)
    return network


class FullQueueBus(can.BusABC):  # type: ignore[misc]
    """A python-can bus whose first ``refusals`` sends fail as SocketCAN's do on a full transmit
    queue (python-can raises CanOperationError with the errno; the kernel tier makes a real one
    with a qdisc, tests/test_kernel_tier.py), then sends to a virtual bus."""

    def __init__(self, refusals: int) -> None:
        super().__init__(channel="full")
        self.refusals = refusals
        self.out = can.Bus(interface="virtual", channel="full-queue")
        self.sent: list[can.Message] = []

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.refusals:
            self.refusals -= 1
            raise can.CanOperationError("Failed to transmit: No buffer space available", errno.ENOBUFS)
        self.sent.append(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return self.out.recv(timeout), False

    def shutdown(self) -> None:
        self.out.shutdown()
        super().shutdown()


@pytest.mark.parametrize("refusals", [1, 5])
def test_a_full_transmit_queue_is_retried_and_counted(refusals: int) -> None:
    bus = FullQueueBus(refusals)
    network = GuardedNetwork(bus)
    try:
        told: list[tuple[int, bytes | bytearray, bool]] = []
        network.on_sent = lambda *frame: told.append(frame)
        network.send_message(0x201, b"\x0f\x00")
        assert [m.arbitration_id for m in bus.sent] == [0x201]
        assert (network.tx_queue_full, network.tx_queue_dropped) == (refusals, 0)
        assert told == [(0x201, b"\x0f\x00", False)]  # the flight recorder's: once, after it went out
    finally:
        bus.shutdown()


def test_a_queue_that_stays_full_gives_the_frame_up_with_what_to_check() -> None:
    bus = FullQueueBus(10**9)
    network = GuardedNetwork(bus)
    told: list[tuple[int, bytes | bytearray, bool]] = []
    network.on_sent = lambda *frame: told.append(frame)
    try:
        with pytest.raises(can.CanOperationError, match=r"transmit queue stayed full .* frame 0x201 not sent.*termination"):
            network.send_message(0x201, b"\x0f\x00")
        assert network.tx_queue_dropped == 1 and network.tx_queue_full >= 2 and bus.sent == []
        assert told == []  # a frame given up on is not recorded as sent
        bus.refusals = 0
        network.send_message(0x202, b"")  # the next frame, once it drains
        assert [m.arbitration_id for m in bus.sent] == [0x202] and told == [(0x202, b"", False)]
    finally:
        bus.shutdown()


def test_another_send_error_is_not_taken_for_a_full_queue() -> None:
    assert not queue_full(can.CanOperationError("Failed to transmit: Network is down", errno.ENETDOWN))
    assert queue_full(OSError(errno.ENOBUFS, "No buffer space available"))


def test_python_cans_socketcan_send_on_an_unwritable_socket_is_a_full_queue() -> None:
    """python-can's SocketCAN ``send`` without a timeout (canopen's) raises "Transmit buffer full",
    with no errno, when its socket is not writable: the frames queued in the interface hold the
    socket's send buffer, which with the default txqueuelen of 1000 comes before ENOBUFS. It was
    not taken for a full queue: no retry, no count, the advice on cabling never said (an
    independent review's finding). Its send here on a socket filled until it is not writable (no
    SocketCAN in this kernel; the text is what the check pins)."""
    from can.interfaces.socketcan.socketcan import SocketcanBus

    ours, peer = socket.socketpair()
    try:
        ours.setblocking(False)
        while True:
            try:
                ours.send(bytes(4096))
            except BlockingIOError:
                break
        bus = SocketcanBus.__new__(SocketcanBus)
        bus.socket, bus.channel = ours, "can0"
        with pytest.raises(can.CanOperationError) as refused:
            bus.send(can.Message(arbitration_id=0x201, data=b"\x0f\x00", is_extended_id=False))
        assert queue_full(refused.value), repr(refused.value)
    finally:
        ours.close()
        peer.close()


@given(st.integers(0, 0x7FF), st.booleans(), st.binary(min_size=1, max_size=8),
       st.floats(1_000_000_000, 9_999_999_999))
def test_only_a_frame_without_data_is_as_short_as_a_sync(can_id: int, extended: bool, data: bytes, stamp: float) -> None:
    """hold_lone_sync's mark: every frame with data, as the server writes it, wakes the receive
    thread by itself; a SYNC is exactly the mark's length, and waits."""
    msg = can.Message(arbitration_id=can_id, is_extended_id=extended, data=data, timestamp=stamp)
    assert len(format_frame(msg)) > SYNC_TEXT_BYTES
    sync = can.Message(arbitration_id=0x080, is_extended_id=False, data=b"", timestamp=stamp)
    assert len(format_frame(sync)) == SYNC_TEXT_BYTES


def test_a_held_sync_waits_for_the_next_frame_and_a_frame_with_data_never_waits() -> None:
    sim = SimService([], port=0)
    bus = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
    peer = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
    sock = getattr(bus, SOCKETCAND_SOCKET_ATTRIBUTE)

    def queued() -> int:  # bytes the server has written to the bus's socket, not yet read
        try:
            return len(sock.recv(256, socket.MSG_PEEK | socket.MSG_DONTWAIT))
        except BlockingIOError:
            return 0

    sync = can.Message(arbitration_id=0x080, data=b"", is_extended_id=False)
    beat = can.Message(arbitration_id=0x701, data=b"\x05", is_extended_id=False)
    try:
        assert hold_lone_sync(bus, True)
        peer.send(beat)  # with data, alone: it wakes the thread (a mark too high would hold it)
        assert received_id(bus, 10.0) == 0x701
        peer.send(sync)
        wait_for(lambda: queued() == SYNC_TEXT_BYTES, 10.0, "the SYNC in the bus's socket")
        assert bus.recv(0) is None  # there, and not woken for
        peer.send(beat)
        first, second = bus.recv(10.0), bus.recv(10.0)
        assert first is not None and second is not None
        assert (first.arbitration_id, second.arbitration_id) == (0x080, 0x701)  # nothing lost or reordered
        assert hold_lone_sync(bus, False)
        peer.send(sync)
        assert received_id(bus, 10.0) == 0x080
    finally:
        peer.shutdown()
        bus.shutdown()
        sim.close()
    assert not hold_lone_sync(bus, False)  # closed: nothing to do, no error
    assert not hold_lone_sync(can.Bus(interface="virtual", channel="pin"), True)  # other interfaces


FRAMES = st.lists(st.builds(lambda i, ext, data, t: can.Message(arbitration_id=i, is_extended_id=ext, data=data, timestamp=t),
                            st.integers(0, 0x7FF), st.booleans(), st.binary(max_size=8),
                            st.floats(1_000_000_000, 9_999_999_999)), min_size=1, max_size=12)


@given(FRAMES, st.lists(st.integers(0, 600), max_size=6), st.booleans())
def test_a_batch_read_parses_what_python_can_parses_whatever_the_reads_cut(frames: list[can.Message], cuts: list[int],
                                                                           noise: bool) -> None:
    """batch_receive's one-pass parser against python-can's own converter (the reference): the
    server's text of any frames, cut into reads anywhere, gives the same frames in order (id,
    standard or extended, stamp, data); an ``< ok >`` between them is skipped."""
    texts = [format_frame(m) for m in frames]
    stream = ("< ok >" if noise else "").join(texts)
    expected = [convert_ascii_message_to_can_message(t) for t in texts]
    got: list[can.Message] = []
    rest, start = "", 0
    for cut in [*sorted(c for c in cuts if c < len(stream)), len(stream)]:
        parsed, rest = parse_frames(rest + stream[start:cut], "can0")
        got += parsed
        start = max(start, cut)
    assert rest == ""
    assert [(m.arbitration_id, m.is_extended_id, m.timestamp, bytes(m.data), m.dlc, m.channel) for m in got] == \
        [(m.arbitration_id, m.is_extended_id, m.timestamp, bytes(m.data), m.dlc, "can0") for m in expected]


def test_an_error_frame_is_read_as_python_can_reads_it() -> None:
    text = "< error 20000080 1700000000.250000 >"
    (got,), rest = parse_frames(text, "can0")
    want = convert_ascii_message_to_can_message(text)
    assert rest == "" and got.is_error_frame and want.is_error_frame
    assert (got.arbitration_id, got.timestamp, bytes(got.data)) == (want.arbitration_id, want.timestamp, bytes(want.data))


@pytest.mark.parametrize("bad", ["< frame 18x 1700000000.0 0102 >", "< frame 181 soon 0102 >",
                                 "< frame 181 1700000000.0 01020 >", "< error zz 1700000000.0 >"])
def test_a_frame_that_does_not_parse_is_skipped_and_the_others_kept(bad: str) -> None:
    """One malformed line among good frames (python-can raised on it, and the whole read was lost:
    the receive error took the bus for lost) is skipped; the frames around it and the text a read
    cut in two after it are kept."""
    good = "< frame 181 1700000000.000100 0637 >"
    got, rest = parse_frames(good + bad + good + "< frame 281 17", "can0")
    assert [(m.arbitration_id, bytes(m.data)) for m in got] == [(0x181, b"\x06\x37")] * 2
    assert rest == "< frame 281 17"


def _unconnected_socketcand(sock: socket.socket, tune: bool) -> can.BusABC:
    """python-can's socketcand client around ``sock`` (no server handshake): what its send writes is read at the other end."""
    bus = SocketCanDaemonBus.__new__(SocketCanDaemonBus)
    setattr(bus, SOCKETCAND_SOCKET_ATTRIBUTE, sock)
    setattr(bus, SOCKETCAND_TCP_TUNE, tune)
    return bus


def _tcp_pair() -> tuple[socket.socket, socket.socket]:
    with socket.create_server(("127.0.0.1", 0)) as server:
        client = socket.create_connection(server.getsockname())
        peer, _ = server.accept()
    return client, peer


def _read_text(peer: socket.socket, size: int) -> str:
    got = b""
    while len(got) < size:
        got += peer.recv(size - len(got))
    return got.decode("ascii")


@given(st.lists(st.tuples(st.one_of(st.integers(0, 0x7FF), st.integers(0x800, 0x1FFFFFFF)), st.binary(max_size=8),
                          st.booleans()), min_size=1, max_size=8), st.booleans())
def test_the_direct_send_writes_what_python_can_writes_for_canopens_message(frames: list[tuple[int, bytes, bool]],
                                                                            tune: bool) -> None:
    """Byte for byte the text python-can's socketcand ``send`` writes for the message canopen's
    ``send_message`` makes (an id above 0x7FF extended; a remote frame, which socketcand's rawmode
    cannot carry, written as python-can writes it: no data), on a TCP socket with and without ``tcp_tune``."""
    client, peer = _tcp_pair()
    try:
        direct = socketcand_sender(_unconnected_socketcand(client, tune))
        assert direct is not None
        for can_id, data, remote in frames:
            want = convert_can_message_to_ascii_message(can.Message(is_extended_id=can_id > 0x7FF, arbitration_id=can_id,
                                                                    data=data, is_remote_frame=remote))
            direct.send(can_id, data, remote)
            assert _read_text(peer, len(want)) == want
        texts = [direct.text(*frame) for frame in frames]  # one_write's: the same bytes, in one write
        direct.write(b"".join(texts))
        assert _read_text(peer, sum(map(len, texts))) == "".join(
            convert_can_message_to_ascii_message(can.Message(is_extended_id=can_id > 0x7FF, arbitration_id=can_id,
                                                             data=data, is_remote_frame=remote))
            for can_id, data, remote in frames)
    finally:
        client.close()
        peer.close()


def test_the_direct_send_is_only_for_python_cans_socketcand_send() -> None:
    bus = FullQueueBus(0)  # its own send: the network must call it, not a socket
    try:
        assert socketcand_sender(bus) is None and socketcand_sender(None) is None
        network = GuardedNetwork(bus)
        network.send_message(0x201, b"\x0f")
        assert [m.arbitration_id for m in bus.sent] == [0x201]
    finally:
        bus.shutdown()


def _writes_of(network: GuardedNetwork) -> list[bytes]:
    """A hook on the network's held write to its socket (the write itself real): each one's bytes."""
    network._direct()  # the direct sender, made for the network's bus
    bus, direct = network._sender
    assert direct is not None
    writes: list[bytes] = []

    def write(payload: bytes) -> None:
        writes.append(payload)
        direct.write(payload)
    network._sender = (bus, direct._replace(write=write))
    return writes


def _heard(peer: can.BusABC, count: int) -> list[tuple[int, bytes]]:
    out = []
    for _ in range(count):
        msg = peer.recv(10.0)  # a bound for a hang
        assert msg is not None, f"heard {out}, then nothing"
        out.append((msg.arbitration_id, bytes(msg.data)))
    return out


@pytest.fixture
def held_network() -> Iterator[tuple[SimService, GuardedNetwork, can.BusABC, list[tuple[int, bytes | bytearray, bool]]]]:
    """A network on the simulator's socketcand server, a peer on the same bus, what on_sent was told."""
    sim = SimService([], port=0)
    buses = [can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port) for _ in range(2)]
    network = GuardedNetwork(buses[0])
    told: list[tuple[int, bytes | bytearray, bool]] = []
    network.on_sent = lambda *frame: told.append(frame)
    on_the_bus(sim.server, 2)  # the peer listens before anything is sent
    try:
        yield sim, network, buses[1], told
    finally:
        for bus in buses:
            bus.shutdown()
        sim.close()


def test_frames_of_one_write_go_out_in_one_write_in_order_and_are_told_once_written(
        held_network: tuple[SimService, GuardedNetwork, can.BusABC, list[tuple[int, bytes | bytearray, bool]]]) -> None:
    _, network, peer, told = held_network
    writes = _writes_of(network)
    frames = [(0x301, b"\x0f\x00\x01\x00\x00\x00"), (0x302, b"\x0f\x00\x02\x00\x00\x00"), (0x303, b"\x1f\x00")]
    with network.one_write():
        for can_id, data in frames:
            network.send_message(can_id, data)
        assert told == [] and writes == []  # held: nothing written, nothing told
    assert len(writes) == 1 and writes[0].count(b"< send ") == 3
    assert told == [(can_id, data, False) for can_id, data in frames]
    assert _heard(peer, 3) == frames


def test_another_threads_frame_inside_one_write_goes_out_after_the_frames_held_before_it(
        held_network: tuple[SimService, GuardedNetwork, can.BusABC, list[tuple[int, bytes | bytearray, bool]]]) -> None:
    """The order on the wire is the order of the calls: a stop sent by another thread while a
    SYNC's set-points are held follows the set-points handed over before it (a set-point carrying
    Enable Operation after the stop would undo it), and those after it follow it."""
    _, network, peer, told = held_network
    stop = (0x201, b"\x02\x00")
    with network.one_write():
        network.send_message(0x301, b"\x0f\x00\x01\x00\x00\x00")
        network.send_message(0x302, b"\x0f\x00\x02\x00\x00\x00")
        other = threading.Thread(target=network.send_message, args=stop)
        other.start()
        other.join(10.0)
        assert not other.is_alive()
        # on the wire at once, the held set-points first: not at the block's end
        assert [can_id for can_id, _ in _heard(peer, 3)] == [0x301, 0x302, 0x201]
        network.send_message(0x303, b"\x0f\x00\x03\x00\x00\x00")
    assert [can_id for can_id, _ in _heard(peer, 1)] == [0x303]
    assert [can_id for can_id, _, _ in told] == [0x301, 0x302, 0x201, 0x303]


def test_the_holders_own_sdo_request_goes_out_at_once_after_the_set_points_held(
        held_network: tuple[SimService, GuardedNetwork, can.BusABC, list[tuple[int, bytes | bytearray, bool]]]) -> None:
    """Only RPDOs are held: a thread that sends an SDO request inside its block (a target or a mode
    written by SDO) waits for the answer, so the request goes out now, after what it held."""
    _, network, peer, told = held_network
    with network.one_write():
        network.send_message(0x301, b"\x0f\x00\x01\x00\x00\x00")
        network.send_message(0x601, b"\x2f\x60\x60\x00\x08\x00\x00\x00")
        assert [can_id for can_id, _ in _heard(peer, 2)] == [0x301, 0x601]
        network.send_message(0x302, b"\x0f\x00\x02\x00\x00\x00")
    assert [can_id for can_id, _ in _heard(peer, 1)] == [0x302]
    assert [can_id for can_id, _, _ in told] == [0x301, 0x601, 0x302]


def test_held_frames_another_threads_write_lost_are_said_to_the_holder(
        held_network: tuple[SimService, GuardedNetwork, can.BusABC, list[tuple[int, bytes | bytearray, bool]]]) -> None:
    """The write of the held frames fails in another thread's send (a hook on the write: the
    socket's error): that send raises, and the holder, whose frames were lost, is told at its end."""
    _, network, _, told = held_network
    bus, direct = network._sender if network._direct() else (None, None)
    assert direct is not None

    def write(payload: bytes) -> None:
        raise OSError(errno.EPIPE, "Broken pipe")
    failures: list[BaseException] = []

    def stop() -> None:
        try:
            network.send_message(0x201, b"\x02\x00")
        except OSError as err:
            failures.append(err)
    with pytest.raises(can.CanOperationError, match=r"1 frame\(s\) held not sent: .*Broken pipe"), network.one_write():
        network.send_message(0x301, b"\x0f\x00\x01\x00\x00\x00")
        network._sender = (bus, direct._replace(write=write))
        other = threading.Thread(target=stop)
        other.start()
        other.join(10.0)
        network._sender = (bus, direct)
    assert len(failures) == 1 and network.held_dropped == 1 and told == []


def test_frames_held_for_a_bus_since_replaced_are_dropped_and_the_holder_told(
        held_network: tuple[SimService, GuardedNetwork, can.BusABC, list[tuple[int, bytes | bytearray, bool]]]) -> None:
    """A reconnect while frames are held: they were for the old connection (drives booted again since)
    and are not written to the new one; the holder's end raises, another thread's frame goes out."""
    sim, network, peer, told = held_network
    second = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
    try:
        on_the_bus(sim.server, 3)
        with pytest.raises(can.CanOperationError, match="replaced"), network.one_write():
            network.send_message(0x301, b"\x0f\x00\x01\x00\x00\x00")
            network.bus = second
        assert network.held_dropped == 1 and told == []
        with pytest.raises(can.CanOperationError, match="replaced"), network.one_write():
            network.send_message(0x302, b"\x0f\x00\x02\x00\x00\x00")
            network.bus = peer
            other = threading.Thread(target=network.send_message, args=(0x201, b"\x02\x00"))
            other.start()
            other.join(10.0)
        assert network.held_dropped == 2
        assert second.recv(10.0) is not None  # the stop, sent by the replacement (the peer's own socket)
        assert [can_id for can_id, _, _ in told] == [0x201]
    finally:
        second.shutdown()


def test_one_write_is_each_frame_at_once_where_the_bus_is_not_socketcand() -> None:
    bus = FullQueueBus(0)
    try:
        network = GuardedNetwork(bus)
        with network.one_write():
            network.send_message(0x301, b"\x0f\x00")
            assert [m.arbitration_id for m in bus.sent] == [0x301]
    finally:
        bus.shutdown()


def test_a_network_sends_on_the_server_directly_and_on_the_new_bus_after_a_reconnect() -> None:
    """End to end on the simulator's socketcand server: what the network sends, a peer hears; given
    a new bus (a reconnect), the network writes to the new one, not the old socket."""
    sim = SimService([], port=0)
    buses = [can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port) for _ in range(3)]
    first, second, peer = buses
    network = GuardedNetwork(first)
    try:
        on_the_bus(sim.server, 3)  # the peer listens before anything is sent
        told: list[tuple[int, bytes | bytearray, bool]] = []
        network.on_sent = lambda *frame: told.append(frame)
        network.send_message(0x201, b"\x0f\x00\x10\x27")
        assert network._sender[0] is first and network._sender[1] is not None  # the direct path, not canopen's
        heard = peer.recv(10.0)
        assert heard is not None and (heard.arbitration_id, bytes(heard.data)) == (0x201, b"\x0f\x00\x10\x27")
        first.shutdown()
        network.bus = second
        on_the_bus(sim.server, 2)
        network.send_message(0x12345, b"")
        assert network._sender[0] is second and network._sender[1] is not None
        heard = peer.recv(10.0)
        assert heard is not None and (heard.arbitration_id, heard.is_extended_id, heard.dlc) == (0x12345, True, 0)
        assert told == [(0x201, b"\x0f\x00\x10\x27", False), (0x12345, b"", False)]
    finally:
        for bus in buses:
            bus.shutdown()
        sim.close()


def test_each_one_write_writes_every_bus_whatever_another_s_write_did() -> None:
    """Several buses held at once (a trajectory group's SYNC, a /joint_commands message): one bus's
    write failing is named in the list yielded (the frames lost named), the other bus's set-points
    still go out; any other error of one bus (its receive thread's death) is listed with its bus,
    the frames written; a body that raises still writes both and leaves no holder."""
    sim = SimService([], port=0, extra_channels=("can0", "can1"))
    buses = {ch: [can.Bus(interface="socketcand", channel=ch, host=sim.host, port=sim.port) for _ in range(2)]
             for ch in ("can0", "can1")}
    try:
        networks = {ch: GuardedNetwork(pair[0]) for ch, pair in buses.items()}
        on_the_bus(sim.server, 4)
        writes = _writes_of(networks["can1"])
        bus, direct = networks["can0"]._sender if networks["can0"]._direct() else (None, None)
        assert direct is not None

        def broken(payload: bytes) -> None:
            raise OSError(errno.EPIPE, "Broken pipe")
        networks["can0"]._sender = (bus, direct._replace(write=broken))
        with GuardedNetwork.each_one_write(sorted(networks.items())) as failed:
            networks["can0"].send_message(0x301, b"\x0f\x00\x01\x00\x00\x00")
            networks["can1"].send_message(0x302, b"\x0f\x00\x02\x00\x00\x00")
            networks["can1"].send_message(0x303, b"\x0f\x00\x03\x00\x00\x00")
            assert failed == [] and writes == []
        assert [name for name, _ in failed] == ["can0"] and "Broken pipe" in str(failed[0][1])
        assert isinstance(failed[0][1], HeldFramesLost) and failed[0][1].can_ids == (0x301,), failed
        assert len(writes) == 1 and _heard(buses["can1"][1], 2) == [(0x302, b"\x0f\x00\x02\x00\x00\x00"),
                                                                    (0x303, b"\x0f\x00\x03\x00\x00\x00")]
        networks["can0"]._sender = (bus, direct)

        def dead() -> None:
            raise RuntimeError("the receive thread died")
        networks["can0"].check = dead  # type: ignore[method-assign]
        with GuardedNetwork.each_one_write(sorted(networks.items())) as failed:
            networks["can0"].send_message(0x304, b"\x0f\x00\x04\x00\x00\x00")
            networks["can1"].send_message(0x305, b"\x0f\x00\x05\x00\x00\x00")
        # named with its bus, for the caller to say or raise: not raised in place of the other bus's write
        assert [(name, str(err)) for name, err in failed] == [("can0", "the receive thread died")], failed
        assert _heard(buses["can1"][1], 1) == [(0x305, b"\x0f\x00\x05\x00\x00\x00")]
        assert _heard(buses["can0"][1], 1) == [(0x304, b"\x0f\x00\x04\x00\x00\x00")]  # written, then judged

        def gone() -> None:  # the receive thread ended on the socket's error: the frames were written
            raise can.CanOperationError("Failed to receive: connection reset")
        networks["can0"].check = gone  # type: ignore[method-assign]
        with pytest.raises(ValueError, match="the body's"), \
                GuardedNetwork.each_one_write(sorted(networks.items())) as failed:
            networks["can0"].send_message(0x306, b"\x0f\x00\x06\x00\x00\x00")
            networks["can1"].send_message(0x307, b"\x0f\x00\x07\x00\x00\x00")
            raise ValueError("the body's own error")
        assert [name for name, _ in failed] == ["can0"] and not isinstance(failed[0][1], HeldFramesLost), failed
        assert _heard(buses["can0"][1], 1) == [(0x306, b"\x0f\x00\x06\x00\x00\x00")]
        assert _heard(buses["can1"][1], 1) == [(0x307, b"\x0f\x00\x07\x00\x00\x00")]
        assert all(n._holder is None for n in networks.values())
    finally:
        for pair in buses.values():
            for each in pair:
                each.shutdown()
        sim.close()
