"""The bus server's accept loop survives any one connection's failure: with every slot full,
clients that connect and reset at once do not stop it, and a well-behaved client connects as soon
as a slot is free."""

from __future__ import annotations

import socket
import struct
import time

import can

from virtual_can import BusEngine, SocketcandServer
from virtual_can.server import DEFAULT_MAX_CLIENTS

from .conftest import wait_for


def resetting_connect(port: int) -> None:
    """Connect and close with a TCP reset (linger 0) before the server answers."""
    sock = socket.create_connection(("127.0.0.1", port))
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    sock.close()


def test_full_slots_and_resetting_clients_do_not_end_the_accept_loop() -> None:
    with BusEngine() as engine, SocketcandServer(engine, port=0, channels=("can0",)) as srv:
        held = [socket.create_connection(("127.0.0.1", srv.port)) for _ in range(DEFAULT_MAX_CLIENTS)]
        try:
            wait_for(lambda: len(srv.clients) == DEFAULT_MAX_CLIENTS, 5.0, "every slot taken")
            for _ in range(20):
                resetting_connect(srv.port)
            time.sleep(0.2)
            assert srv._thread.is_alive()  # the accept loop runs on
            for sock in held[:2]:
                sock.close()
            wait_for(lambda: len(srv.clients) <= DEFAULT_MAX_CLIENTS - 2, 5.0, "two slots free")
            with socket.create_connection(("127.0.0.1", srv.port), timeout=2.0) as good:
                assert good.recv(64).startswith(b"< hi >")
            with can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=srv.port) as a, \
                    can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=srv.port) as b:
                time.sleep(0.1)
                a.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))
                got = b.recv(2.0)
                assert got is not None and got.arbitration_id == 0x123  # and it reads frames
        finally:
            for sock in held:
                sock.close()
