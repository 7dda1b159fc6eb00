"""Pins the dependency internals motor_driver/adapters.py relies on, against the installed
python-can and canopen: an upgrade that changes them fails here, not on the rover."""

from __future__ import annotations

import inspect
import socket
import time

import can
import canopen
import pytest

from motor_driver.adapters import SOCKETCAND_SOCKET_ATTRIBUTE, GuardedNetwork, connection_closed
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
