"""The bus server's cyclic jobs: limited per client (and in all), each job on its own schedule
whatever else waits in the timer's heap, and a deleted or replaced job never sent again. The
timing under 50,000 idle jobs is a benchmark (benchmarks/cyclic_jobs.py), not a test."""

from __future__ import annotations

import socket
import time

import can

from virtual_can import BusEngine, SocketcandServer

from .conftest import wait_for


def bcm_client(port: int) -> socket.socket:
    sock = socket.create_connection(("127.0.0.1", port), timeout=2.0)
    assert sock.recv(64).startswith(b"< hi >")
    sock.sendall(b"< open can0 >")
    assert sock.recv(64).startswith(b"< ok >")
    return sock


def replies(sock: socket.socket) -> bytes:
    sock.sendall(b"< echo >")
    got = b""
    while not got.endswith(b"< echo >"):
        got += sock.recv(4096)
    return got


def test_a_client_over_its_job_limit_is_refused_and_another_is_not() -> None:
    with BusEngine() as engine, SocketcandServer(engine, port=0) as srv:
        srv.cyclic.max_per_client = 10
        hostile, other = bcm_client(srv.port), bcm_client(srv.port)
        try:
            hostile.sendall(b"".join(f"< add 3600 0 {0x100 + i:03X} 1 00 >".encode() for i in range(12)))
            got = replies(hostile)
            assert got.count(b"too many cyclic jobs (this client has 10)") == 2, got
            hostile.sendall(b"< add 1 0 100 1 01 >")  # replacing a job it has is not a new one
            assert b"error" not in replies(hostile)
            other.sendall(b"< add 3600 0 200 1 00 >")
            assert b"error" not in replies(other)
            assert len(srv.cyclic) == 11
            srv.cyclic.max_total = 11
            other.sendall(b"< add 3600 0 201 1 00 >")
            assert b"too many cyclic jobs (the server has 11)" in replies(other)
        finally:
            hostile.close()
            other.close()
        wait_for(lambda: len(srv.cyclic) == 0, 5.0, "the jobs gone with their clients")


def test_each_job_keeps_its_period_among_many_idle_ones_and_a_deleted_one_stops() -> None:
    with BusEngine() as engine, SocketcandServer(engine, port=0) as srv, \
            can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=srv.port) as listener:
        jobs = bcm_client(srv.port)
        try:
            jobs.sendall(b"".join(f"< add 3600 0 {0x1000_0000 + i:08X} 1 00 >".encode() for i in range(2000)))
            jobs.sendall(b"< add 0 20000 181 1 01 >< add 0 50000 182 1 02 >< add 0 10000 183 1 03 >")
            assert b"error" not in replies(jobs)
            time.sleep(0.3)
            jobs.sendall(b"< delete 183 >< add 0 10000 182 1 04 >")  # 183 stops; 182 replaced: 10 ms, new data
            assert b"error" not in replies(jobs)
            changed = time.time()
            seen: dict[int, list[can.Message]] = {}
            until = time.monotonic() + 1.0
            while time.monotonic() < until:
                msg = listener.recv(0.1)
                if msg is not None and not msg.is_extended_id and msg.timestamp > changed + 0.005:
                    seen.setdefault(msg.arbitration_id, []).append(msg)
        finally:
            jobs.close()

        def period_ms(can_id: int) -> float:
            stamps = [m.timestamp for m in seen[can_id]]
            return (stamps[-1] - stamps[0]) / (len(stamps) - 1) * 1000

        assert abs(period_ms(0x181) - 20) < 1.0
        assert abs(period_ms(0x182) - 10) < 1.0 and {bytes(m.data) for m in seen[0x182]} == {b"\x04"}
        assert 0x183 not in seen
