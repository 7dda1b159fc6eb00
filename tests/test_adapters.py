"""Pins the dependency internals motor_driver/adapters.py relies on, against the installed
python-can and canopen: an upgrade that changes them fails here, not on the rover."""

from __future__ import annotations

import errno
import inspect
import socket
import time

import can
import canopen
import pytest

from motor_driver.adapters import SOCKETCAND_SOCKET_ATTRIBUTE, GuardedNetwork, connection_closed, queue_full
from virtual_can import SimService


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
        network.send_message(0x201, b"\x0f\x00")
        assert [m.arbitration_id for m in bus.sent] == [0x201]
        assert (network.tx_queue_full, network.tx_queue_dropped) == (refusals, 0)
    finally:
        bus.shutdown()


def test_a_queue_that_stays_full_gives_the_frame_up_with_what_to_check() -> None:
    bus = FullQueueBus(10**9)
    network = GuardedNetwork(bus)
    try:
        with pytest.raises(can.CanOperationError, match=r"transmit queue stayed full .* frame 0x201 not sent.*termination"):
            network.send_message(0x201, b"\x0f\x00")
        assert network.tx_queue_dropped == 1 and network.tx_queue_full >= 2 and bus.sent == []
        bus.refusals = 0
        network.send_message(0x202, b"")  # the next frame, once it drains
        assert [m.arbitration_id for m in bus.sent] == [0x202]
    finally:
        bus.shutdown()


def test_another_send_error_is_not_taken_for_a_full_queue() -> None:
    assert not queue_full(can.CanOperationError("Failed to transmit: Network is down", errno.ENETDOWN))
    assert queue_full(OSError(errno.ENOBUFS, "No buffer space available"))
