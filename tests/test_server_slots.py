"""The bus server's slots: the accept loop survives any one connection's failure (with every
slot full, clients that connect and reset at once do not stop it), and connections that hold a
slot without a word give it to a newcomer once silent for the idle time, while the driver's own
cyclic-job connection, which keeps itself heard, keeps its slot."""

from __future__ import annotations

import socket
import struct
import time

import can
import pytest

from motor_driver.bus import cyclic
from virtual_can import BusEngine, SocketcandServer
from virtual_can.server import DEFAULT_MAX_CLIENTS

from .conftest import on_the_bus, received_id, wait_for


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
            with socket.create_connection(("127.0.0.1", srv.port), timeout=2.0) as marker:  # accepted after them
                assert marker.recv(64) == b"< error too many clients >"
            assert srv._thread.is_alive()  # the accept loop runs on
            for sock in held[:2]:
                sock.close()
            wait_for(lambda: len(srv.clients) <= DEFAULT_MAX_CLIENTS - 2, 5.0, "two slots free")
            with socket.create_connection(("127.0.0.1", srv.port), timeout=2.0) as good:
                assert good.recv(64).startswith(b"< hi >")
            # its slot is free once the server saw it close (the next two clients need both)
            wait_for(lambda: len(srv.clients) <= DEFAULT_MAX_CLIENTS - 2, 5.0, "the good client's slot free again")
            with can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=srv.port) as a, \
                    can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=srv.port) as b:
                on_the_bus(srv, 2)
                a.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))
                assert received_id(b, 2.0) == 0x123  # and it reads frames
        finally:
            for sock in held:
                sock.close()


def hostile(port: int, mode: str) -> socket.socket:
    """A connection that takes a slot and then says nothing: in rawmode, or in BCM mode holding
    a one-hour cyclic job."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=2.0)
    sock.recv(64)  # < hi >
    sock.sendall(b"< open can0 >")
    sock.recv(64)  # < ok >
    sock.sendall(b"< rawmode >" if mode == "raw" else b"< add 3600 0 7FF 1 00 >")
    return sock


def test_idle_hostile_connections_give_way_to_a_well_behaved_client() -> None:
    """64 connections that hold every slot and never speak (half in rawmode, half in BCM mode
    with a cyclic job): once they have been silent for the idle time, a new client connects and
    receives within 1 s, and the silent longest go first. (The server's default idle time is
    IDLE_TIMEOUT_S; the test uses a short one.)"""
    idle_s = 0.5
    with BusEngine() as engine, SocketcandServer(engine, port=0, channels=("can0",), idle_timeout_s=idle_s) as srv:
        held = [hostile(srv.port, "raw" if i % 2 else "bcm") for i in range(DEFAULT_MAX_CLIENTS)]
        try:
            wait_for(lambda: len(srv.clients) == DEFAULT_MAX_CLIENTS, 5.0, "every slot taken")
            with socket.create_connection(("127.0.0.1", srv.port), timeout=2.0) as early:
                assert early.recv(64).startswith(b"< error too many clients >")  # not yet idle long enough
            time.sleep(idle_s + 0.1)
            for _ in range(3):  # each newcomer takes the slot of one hostile connection
                started = time.monotonic()
                with can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=srv.port) as a, \
                        can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=srv.port) as b:
                    time.sleep(0.1)
                    a.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))
                    assert received_id(b, 1.0) == 0x123
                    assert time.monotonic() - started < 1.5
            assert srv.idle_closed >= 2
        finally:
            for sock in held:
                sock.close()


def test_the_driver_s_cyclic_job_is_never_taken_for_idle(monkeypatch: pytest.MonkeyPatch) -> None:
    """The driver's SYNC connection (BCM mode, nothing to say after its '< add >') keeps its slot:
    its keep-alive echo makes it heard, so newcomers take the silent hostile slots instead."""
    monkeypatch.setattr(cyclic, "KEEPALIVE_S", 0.1)
    idle_s = 0.5
    with BusEngine() as engine, SocketcandServer(engine, port=0, channels=("can0",), idle_timeout_s=idle_s) as srv:
        task = cyclic.DaemonCyclicTask("127.0.0.1", srv.port, "can0",
                                       can.Message(arbitration_id=0x080, data=b"", is_extended_id=False), 0.01)
        held = [hostile(srv.port, "bcm") for _ in range(DEFAULT_MAX_CLIENTS - 1)]
        try:
            wait_for(lambda: len(srv.clients) == DEFAULT_MAX_CLIENTS, 5.0, "every slot taken")
            task_client = max(srv.clients, key=srv.cyclic.last_sent)  # the one whose job runs

            def hostile_idle() -> bool:  # by the server's own measure, as its slot rule judges
                assert task.keep_alive(time.monotonic())
                now = time.monotonic()
                return all(now - max(c.last_active, srv.cyclic.last_sent(c)) > idle_s + 0.1
                           for c in srv.clients if c is not task_client)

            wait_for(hostile_idle, 30.0, "every hostile connection idle past the idle timeout")
            newcomers = []
            for _ in range(DEFAULT_MAX_CLIENTS - 1):  # every hostile slot is taken over, one by one
                assert task.keep_alive(time.monotonic())
                newcomers.append(socket.create_connection(("127.0.0.1", srv.port), timeout=2.0))
                assert newcomers[-1].recv(64).startswith(b"< hi >")
            assert srv.idle_closed == DEFAULT_MAX_CLIENTS - 1
            for sock in newcomers[:2]:
                sock.close()
            wait_for(lambda: len(srv.clients) < DEFAULT_MAX_CLIENTS, 5.0, "a slot free")
            with can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=srv.port) as listener:
                syncs, deadline = 0, time.monotonic() + 30.0
                while syncs < 10:  # the SYNC runs on
                    assert time.monotonic() < deadline, f"{syncs} SYNCs in 30 s"
                    msg = listener.recv(0.1)
                    syncs += msg is not None and msg.arbitration_id == 0x080
            for sock in newcomers:
                sock.close()
            assert task.keep_alive(time.monotonic())
        finally:
            task.stop()
            for sock in held:
                sock.close()


def test_echoing_clients_give_way_to_a_newcomer() -> None:
    """64 connections that hold every slot and say '< echo >' over and over (the attack: one
    echo every 20 s held every slot for ever): an echo is no frame and no command, so once the
    idle time has passed a newcomer gets a slot, and an echoer gives way."""
    idle_s = 0.5
    with BusEngine() as engine, SocketcandServer(engine, port=0, channels=("can0",), idle_timeout_s=idle_s) as srv:
        held = [hostile(srv.port, "raw") for _ in range(DEFAULT_MAX_CLIENTS)]
        try:
            wait_for(lambda: len(srv.clients) == DEFAULT_MAX_CLIENTS, 5.0, "every slot taken")
            deadline = time.monotonic() + 10.0  # a hang, not a timing claim
            while True:
                for sock in held:  # echo, echo: keeping every connection "heard"
                    try:
                        sock.sendall(b"< echo >")
                    except OSError:
                        pass  # this one was given away already
                with socket.create_connection(("127.0.0.1", srv.port), timeout=2.0) as newcomer:
                    if newcomer.recv(64).startswith(b"< hi >"):
                        break
                assert time.monotonic() < deadline, "no slot ever freed from the echoing clients"
                time.sleep(0.05)  # the echoes' pace
            assert srv.idle_closed >= 1
        finally:
            for sock in held:
                sock.close()


def job_socket(port: int) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=2.0)
    sock.recv(64)  # < hi >
    sock.sendall(b"< open can0 >")
    sock.recv(64)  # < ok >
    return sock


def add(sock: socket.socket, can_id: int, period_us: int) -> bytes:
    """'< add >' a job; what the server answers within 0.3 s (nothing: accepted)."""
    sock.sendall(f"< add 0 {period_us} {can_id:X} 1 00 >".encode())
    sock.settimeout(0.3)
    try:
        return sock.recv(256)
    except TimeoutError:
        return b""


def test_a_clients_cyclic_jobs_have_a_frame_rate_budget() -> None:
    """The cyclic jobs of one client send at most 2,000 frames a second together (a quarter of
    a 1 Mbit/s bus): 65,536 one-second jobs, or 1,000 jobs at 0.5 ms, starved another client's
    SYNC. Past the budget a job is refused with what it would cost; another client keeps its own."""
    with BusEngine() as engine, SocketcandServer(engine, port=0, channels=("can0",)) as srv:
        greedy, other = job_socket(srv.port), job_socket(srv.port)
        try:
            assert add(greedy, 0x100, 1000) == b""  # 1,000 frames/s
            assert add(greedy, 0x101, 1000) == b""  # 2,000 frames/s: the budget
            refused = add(greedy, 0x102, 1000)
            assert b"would send 3000 frames/s, over its 2000" in refused, refused
            assert add(greedy, 0x101, 2000) == b""  # replacing a job counts its new period only: 1,500
            assert add(greedy, 0x103, 2000) == b""  # 2,000 again
            assert add(other, 0x080, 1000) == b""  # another client's SYNC has a budget of its own
            assert b"over its 2000" in add(greedy, 0x104, 500)  # 0.5 ms: 2,000 frames/s by itself
        finally:
            greedy.close()
            other.close()
