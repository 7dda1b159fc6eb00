"""The bus server's cyclic jobs: limited per client (and in all), each job on its own schedule
whatever else waits in the timer's heap, and a deleted or replaced job never sent again. The
timing under 65,536 idle jobs is a benchmark (benchmarks/cyclic_jobs.py), not a test."""

from __future__ import annotations

import itertools
import math
import os
import signal
import socket
import statistics
import subprocess
import sys
import time
from pathlib import Path

import can

from virtual_can import BusEngine, SocketcandServer

from .conftest import REPO, received_id, wait_for
from .test_sim_cli import free_port


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
            wait_for(lambda: received_id(listener, HANG_S) == 0x183, HANG_S, "job 0x183 running before its delete")
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

        def period_ms(can_id: int) -> float:  # the median gap: one frame a busy machine sent late moves it not
            stamps = [m.timestamp for m in seen[can_id]]
            return statistics.median(b - a for a, b in itertools.pairwise(stamps)) * 1000

        assert abs(period_ms(0x181) - 20) < 1.0
        assert abs(period_ms(0x182) - 10) < 1.0 and {bytes(m.data) for m in seen[0x182]} == {b"\x04"}
        assert 0x183 not in seen


def process_gone(pid: int) -> bool:
    """No such process, or a zombie nobody reaped (the container's init may not)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()[0] == "Z"
    except OSError:
        return True


def syncs_after(listener: can.BusABC, count: int, since: float = -math.inf) -> list[can.Message]:
    """The next ``count`` SYNC frames the listener hears on the bus after ``since`` (time.time();
    earlier ones still on their way are passed over; a hang is the test's timeout)."""
    seen: list[can.Message] = []
    while len(seen) < count:
        msg = listener.recv(HANG_S)
        assert msg is not None, f"no SYNC for {HANG_S} s"
        if msg.arbitration_id == 0x080 and msg.timestamp > since:
            seen.append(msg)
    return seen


HANG_S = 10.0


def test_a_killed_timer_process_is_started_again_with_every_job_and_a_closed_server_ends_it() -> None:
    """The timer is a process of its own (nothing of the server's delays a tick): if it dies the
    server says so and starts another, which is told every job; closing the server ends it."""
    with BusEngine() as engine, SocketcandServer(engine, port=0) as srv, \
            can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=srv.port) as listener:
        jobs = bcm_client(srv.port)
        try:
            assert srv.cyclic.timer_pid is None  # no job, no timer
            jobs.sendall(b"< add 0 10000 080 0 >< add 3600 0 181 1 01 >")
            assert b"error" not in replies(jobs)
            syncs_after(listener, 3)
            first = srv.cyclic.timer_pid
            assert first is not None
            os.kill(first, signal.SIGKILL)
            wait_for(lambda: srv.cyclic.restarts == 1, HANG_S, "a new timer")
            second = srv.cyclic.timer_pid
            assert second not in (None, first)
            syncs_after(listener, 3, since=time.time())  # the SYNC job was handed to the new timer
        finally:
            jobs.close()
        assert second is not None
    wait_for(lambda: process_gone(second), HANG_S, "the timer ended with its server")


def test_a_killed_server_takes_its_timer_process_with_it() -> None:
    """A server killed outright (no close) leaves no timer behind: the timer ends when its socket
    to the server closes."""
    port = free_port()
    sim = subprocess.Popen([sys.executable, "-m", "rovercan", "sim", "--drives", "1", "--port", str(port)], cwd=REPO,
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    kids: list[int] = []
    try:
        assert sim.stdout is not None and "simulated drive" in sim.stdout.readline()
        jobs = bcm_client(port)
        jobs.sendall(b"< add 0 10000 080 0 >")
        assert b"error" not in replies(jobs)
        wait_for(lambda: bool(children(sim.pid)), HANG_S, "the timer process")
        kids += children(sim.pid)
        jobs.close()
    finally:
        sim.kill()
        sim.wait(HANG_S)
    wait_for(lambda: all(process_gone(pid) for pid in kids), HANG_S, "the timer gone with its server")


def children(pid: int) -> list[int]:
    return [int(kid) for task in Path(f"/proc/{pid}/task").glob("*")
            for kid in (task / "children").read_text().split()]


def test_a_scheduled_frame_goes_on_the_bus_at_its_time_before_any_later_frame() -> None:
    """The broadcast manager's frames are scheduled ahead with their bus time (the timer's tick
    comes early): one goes on the channel before the first frame stamped at or after its time
    (whoever delivers it), or when flushed at its time; frames stamped before it go first."""
    with BusEngine() as engine:
        channel = engine.channel("can0")
        heard: list[tuple[int, float]] = []
        channel.attach(lambda m: heard.append((m.arbitration_id, m.timestamp)), "listener")
        sender = channel.attach(lambda m: None, "sender")
        base = time.time() + 100.0  # bus times ahead of now: only frames and flushes move them
        channel.schedule(can.Message(arbitration_id=0x080, timestamp=base + 0.010, is_extended_id=False))
        channel.schedule(can.Message(arbitration_id=0x080, timestamp=base + 0.020, is_extended_id=False))
        sender.send(can.Message(arbitration_id=0x181, timestamp=base + 0.005, is_extended_id=False))
        assert heard == [(0x181, base + 0.005)]  # before the SYNC's time: the SYNC waits
        sender.send(can.Message(arbitration_id=0x182, timestamp=base + 0.010, is_extended_id=False))
        assert heard[1:] == [(0x080, base + 0.010), (0x182, base + 0.010)]  # the SYNC first, at its time
        channel.flush_scheduled(base + 0.015)
        assert len(heard) == 3  # the second SYNC's time has not come
        channel.flush_scheduled(base + 0.020)
        assert heard[3:] == [(0x080, base + 0.020)]
        sender.send(can.Message(arbitration_id=0x183, timestamp=base + 0.019, is_extended_id=False))
        assert heard[4:] == [(0x183, base + 0.020)]  # late to the server: after the SYNC, never stamped before it


def test_ticks_the_server_was_too_stalled_to_take_are_dropped_not_sent_as_a_burst() -> None:
    """While the server cannot take its timer's ticks (here its jobs' lock is held, as a starved
    interpreter would), the timer goes on ticking; afterwards the backlog is not put on the bus:
    a driver counting SYNCs took such a burst for another master's."""
    with BusEngine() as engine, SocketcandServer(engine, port=0) as srv, \
            can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=srv.port) as listener:
        jobs = bcm_client(srv.port)
        try:
            jobs.sendall(b"< add 0 10000 080 0 >")
            assert b"error" not in replies(jobs)
            syncs_after(listener, 3)
            with srv.cyclic._lock:  # the tick reader waits here; the timer's ticks queue up
                held_from = time.time()
                while time.time() < held_from + 0.3:  # thirty periods held
                    pass
                held_to = time.time()
            after = syncs_after(listener, 35)  # the backlog would be about thirty
        finally:
            jobs.close()
    stale = [m.timestamp for m in after if held_from + 0.02 < m.timestamp < held_to - 0.02]
    assert len(stale) <= 1, f"{len(stale)} SYNCs from the stall put on the bus afterwards"
