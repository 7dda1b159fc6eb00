"""The socketcand server at the protocol level: what python-can's client relies on, and a
hostile client affecting only itself."""

from __future__ import annotations

import itertools
import os
import shutil
import socket
import statistics
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from can_config.errors import ProtocolError
from can_config.realtime import SIM_PRIORITY, fifo_thread_count
from virtual_can import BusEngine, SocketcandServer, VirtualBus
from virtual_can.server import format_frame, parse_send
from virtual_can.wire import frame_bits

from .conftest import REPO, drain, heard_before_marker, on_the_bus, realtime_allowed, received_id, wait_for


@pytest.fixture
def server() -> Iterator[SocketcandServer]:
    with BusEngine() as engine, SocketcandServer(engine, port=0, channels=("can0", "can1")) as srv:
        yield srv


def raw_client(srv: SocketcandServer) -> socket.socket:
    sock = socket.create_connection((srv.host, srv.port), timeout=2.0)
    return sock


def read_until(sock: socket.socket, text: str, timeout_s: float = 2.0) -> str:
    data = ""
    deadline = time.monotonic() + timeout_s
    while text not in data and time.monotonic() < deadline:
        try:
            data += sock.recv(4096).decode()
        except TimeoutError:
            break
    return data


def test_handshake_replies_are_separate_writes(server: SocketcandServer) -> None:
    sock = raw_client(server)
    assert sock.recv(256) == b"< hi >"
    sock.sendall(b"< open can0 >")
    assert sock.recv(256) == b"< ok >"
    sock.sendall(b"< rawmode >")
    assert sock.recv(256) == b"< ok >"
    sock.sendall(b"< echo >")
    assert sock.recv(256) == b"< echo >"
    sock.sendall(b"< bogus >")
    assert sock.recv(256) == b"< error unknown command >"
    sock.close()


def test_frame_formats() -> None:
    std = can.Message(arbitration_id=0x123, data=bytes.fromhex("11223344"), is_extended_id=False, timestamp=23.424242)
    assert format_frame(std) == "< frame 123 23.424242 11223344 >"
    ext = can.Message(arbitration_id=0x1ABCDEF, data=b"", is_extended_id=True, timestamp=1.5)
    assert format_frame(ext) == "< frame 01ABCDEF 1.500000  >"
    msg = parse_send("< send 601 8 40 0 10 0 0 0 0 0 >")
    assert msg.arbitration_id == 0x601 and bytes(msg.data) == bytes.fromhex("4000100000000000")
    assert parse_send("< send 00000123 1 ff >").is_extended_id


def test_frames_reach_every_other_client_in_order(server: SocketcandServer) -> None:
    a = can.Bus(interface="socketcand", channel="can0", host=server.host, port=server.port)
    b = can.Bus(interface="socketcand", channel="can0", host=server.host, port=server.port)
    other = can.Bus(interface="socketcand", channel="can1", host=server.host, port=server.port)
    try:
        on_the_bus(server, 3)
        for i in range(500):
            a.send(can.Message(arbitration_id=0x100 + i % 7, data=i.to_bytes(2, "little"), is_extended_id=False))
        got = []
        while len(got) < 500 and (msg := b.recv(2.0)) is not None:
            got.append(int.from_bytes(msg.data, "little"))
        assert got == list(range(500))
        assert other.recv(0.1) is None  # channels are separate
        assert a.recv(0.05) is None  # no echo to the sender
    finally:
        for bus in (a, b, other):
            bus.shutdown()


def test_hostile_client_affects_only_itself(server: SocketcandServer) -> None:
    engine_bus = VirtualBus("can0", engine=server.engine)
    good = can.Bus(interface="socketcand", channel="can0", host=server.host, port=server.port)
    bad = raw_client(server)
    try:
        bad.recv(256)
        bad.sendall(b"< open can0 >")
        bad.recv(256)
        bad.sendall(b"< rawmode >")
        bad.recv(256)
        bad.sendall(b"< send 7FF 9 1 2 >" + b"x" * 5000 + b"< send zz 1 1 >" + b"<" + b"A" * 400)
        reply = read_until(bad, "error")
        assert "< error" in reply
        on_the_bus(server, 2)  # the hostile client is still on it
        engine_bus.send(can.Message(arbitration_id=0x181, data=b"\x01", is_extended_id=False))
        assert received_id(good, 2.0) == 0x181
        good.send(can.Message(arbitration_id=0x201, data=b"\x02", is_extended_id=False))
        assert received_id(engine_bus, 2.0) == 0x201
    finally:
        bad.close()
        good.shutdown()
        engine_bus.shutdown()


def test_half_open_client_is_dropped_and_others_continue(server: SocketcandServer) -> None:
    sock = raw_client(server)
    sock.recv(256)
    sock.sendall(b"< open can0 >")
    sock.close()
    wait_for(lambda: len(server.clients) == 0, 5.0, "the half-open client dropped")
    bus = can.Bus(interface="socketcand", channel="can0", host=server.host, port=server.port)
    bus.shutdown()


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.binary(max_size=300))
def test_fuzzed_lines_never_break_the_server(server: SocketcandServer, junk: bytes) -> None:
    sock = raw_client(server)
    try:
        sock.recv(256)
        sock.sendall(b"< open can0 >< rawmode >" + junk)
    finally:
        sock.close()
    # the server still serves a well-behaved client
    probe = raw_client(server)
    assert probe.recv(256) == b"< hi >"
    probe.close()


def test_frame_bits_worst_case() -> None:
    assert frame_bits(8) == 135  # 8-byte standard frame: 135 us at 1 Mbit/s
    assert frame_bits(0) == 55
    assert frame_bits(8, extended=True) == 160


def test_client_cap_and_slow_client_do_not_hurt_others() -> None:
    import virtual_can.server as server_module
    with BusEngine() as engine, SocketcandServer(engine, port=0, max_clients=2) as srv:
        first = socket.socket()
        first.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a small window: it fills fast
        first.settimeout(2.0)
        first.connect((srv.host, srv.port))
        second = raw_client(srv)
        assert first.recv(256) == b"< hi >" and second.recv(256) == b"< hi >"
        third = raw_client(srv)
        assert third.recv(256) == b"< error too many clients >"  # capped, the others unaffected
        third.close()
        # a client that opened the channel and stopped reading: bounded queue, dropped frames
        first.sendall(b"< open can0 >")
        first.recv(256)
        first.sendall(b"< rawmode >")
        first.recv(256)
        second.close()
        wait_for(lambda: len(srv.clients) == 1, 5.0, "the second client gone")
        slow = [c for c in srv.clients if c.raw]
        assert len(slow) == 1
        good = can.Bus(interface="socketcand", channel="can0", host=srv.host, port=srv.port)
        sender = VirtualBus("can0", engine=engine)
        seen: list[int] = []
        stop = threading.Event()

        def read_good() -> None:
            while not stop.is_set():
                msg = good.recv(0.1)
                if msg is not None:
                    seen.append(msg.arbitration_id)

        reader = threading.Thread(target=read_good, daemon=True)
        reader.start()

        def good_stats() -> object:
            return [(c.stats.sent, c.stats.dropped, c.closed) for c in srv.clients]
        try:
            for i in range(server_module.CLIENT_QUEUE_BYTES // 40 * 10):  # far beyond socket buffers + queue
                sender.send(can.Message(arbitration_id=0x100, data=i.to_bytes(4, "little"), is_extended_id=False))
                if i % 2000 == 0:  # the reading client keeps up, as a real one does (within its queue)
                    paced = time.monotonic() + 2.0
                    while len(seen) < i - 10_000 and time.monotonic() < paced:
                        time.sleep(0.001)
            # the client that does not read loses frames (a bounded queue), and is dropped after
            # SLOW_CLIENT_DROP_LIMIT losses in a row
            wait_until = time.monotonic() + 5.0
            while not slow[0].closed and time.monotonic() < wait_until:
                time.sleep(0.05)
            assert slow[0].stats.dropped >= server_module.SLOW_CLIENT_DROP_LIMIT and slow[0].closed
            sender.send(can.Message(arbitration_id=0x123, data=b"\x01", is_extended_id=False))
            wait_until = time.monotonic() + 5.0
            while 0x123 not in seen and time.monotonic() < wait_until:
                time.sleep(0.05)
            assert 0x123 in seen, (len(seen), good_stats())  # the reading client is still served
        finally:
            stop.set()
            reader.join(2)
            good.shutdown()
            sender.shutdown()
            first.close()


def test_clients_join_a_busy_channel(server: SocketcandServer) -> None:
    """python-can's client reads each handshake reply with one recv(256) and compares it exactly,
    so a frame that arrives with the rawmode '< ok >' fails its connect (the real socketcand has
    the same race). The server holds a new client's frames until it speaks or a moment passes:
    joining a busy bus always works, and the held frames are delivered, not lost."""
    stop = threading.Event()

    def flood() -> None:
        with VirtualBus("can0", engine=server.engine) as sender:
            while not stop.is_set():
                sender.send(can.Message(arbitration_id=0x701, data=b"\x7f", is_extended_id=False))
                time.sleep(0.0002)

    flooder = threading.Thread(target=flood, daemon=True)
    flooder.start()
    try:
        for _ in range(10):
            bus = can.Bus(interface="socketcand", channel="can0", host=server.host, port=server.port)
            try:
                assert bus.recv(2.0) is not None  # held frames arrive once the hold ends
            finally:
                bus.shutdown()
    finally:
        stop.set()
        flooder.join(2.0)


@pytest.mark.parametrize("word", ["+12", "1_0", "0x7FF", "-1", " ", "7FG", "123456789", "١٢٣"])
def test_ids_are_hex_digits_only(word: str) -> None:
    with pytest.raises(ProtocolError, match="hex digits"):
        parse_send(f"< send {word} 1 11 >")


@given(st.integers(0, 0x1FFFFFFF), st.integers(1, 8))
def test_standard_or_extended_by_the_protocol_rule_and_the_value(can_id: int, digits: int) -> None:
    """8 digits (as socketcand and python-can write extended ids) or a value above 0x7FF:
    extended; otherwise standard. Any id python-can formats comes back as it was sent."""
    word = f"{can_id:0{digits}X}"
    if len(word) > 8:
        return
    msg = parse_send(f"< send {word} 0 >")
    assert msg.arbitration_id == can_id
    assert msg.is_extended_id == (len(word) == 8 or can_id > 0x7FF)


def test_a_remote_frame_is_relayed_and_breaks_no_client() -> None:
    """python-can sends an RTR frame as '< send ID DLC >' without data; it is relayed, not refused
    (python-can's client reads any '< error ... >' reply as an error frame and its recv raises)."""
    msg = parse_send("< send 181 2 >")
    assert msg.is_remote_frame and msg.dlc == 2 and not msg.data
    assert format_frame(can.Message(arbitration_id=0x181, is_remote_frame=True, dlc=2, is_extended_id=False,
                                    timestamp=1.0)) == "< frame 181 1.000000  >"


def test_hostile_and_idle_clients_never_starve_a_well_behaved_one() -> None:
    """A client sending non-ASCII, an RTR-sending python-can client and idle connections on every
    free slot: the well-behaved client connects and receives every frame throughout, the idle
    ones are closed once the handshake time is up, and a new client then gets a slot."""
    with BusEngine() as engine, SocketcandServer(engine, port=0, max_clients=6, handshake_timeout_s=1.0) as srv:
        good = can.Bus(interface="socketcand", channel="can0", host=srv.host, port=srv.port)
        sender = VirtualBus("can0", engine=engine)
        stop = threading.Event()
        sent: list[int] = []

        def send_steadily() -> None:
            while not stop.is_set():
                sent.append(len(sent))
                sender.send(can.Message(arbitration_id=0x281, data=sent[-1].to_bytes(4, "little"), is_extended_id=False))
                time.sleep(0.005)

        pump = threading.Thread(target=send_steadily, daemon=True)
        got: list[int] = []
        other_ids: list[tuple[int, bool]] = []
        try:
            on_the_bus(srv, 1)
            pump.start()
            # non-ASCII bytes in a line: the error reply stays ASCII and the client stays served
            rude = raw_client(srv)
            assert rude.recv(256) == b"< hi >"
            rude.sendall(b"< open can0 >")
            rude.recv(256)
            rude.sendall(b"< rawmode >")
            rude.recv(256)
            rude.sendall("< send \u00e9 1 11 >".encode())
            rude.sendall(b"< echo >")
            reply = read_until(rude, "< echo >")
            assert "< error CAN id '\\\\xc3\\\\xa9'" in reply and "< echo >" in reply, reply
            reply.encode("ascii")
            # an RTR frame from python-can: relayed to the others, the sender's recv does not raise
            rtr = can.Bus(interface="socketcand", channel="can0", host=srv.host, port=srv.port)
            rtr.send(can.Message(arbitration_id=0x181, is_remote_frame=True, dlc=2, is_extended_id=False))
            # idle connections on every free slot (good, rude, rtr hold three of six)
            idle = [raw_client(srv) for _ in range(3)]
            for sock in idle:
                assert sock.recv(256) == b"< hi >"
            full = raw_client(srv)
            assert full.recv(256) == b"< error too many clients >"
            full.close()
            start = time.monotonic()
            for sock in idle:
                sock.settimeout(3.0)
                assert sock.recv(256) == b""  # closed by the server
            closed_after = time.monotonic() - start
            late = can.Bus(interface="socketcand", channel="can0", host=srv.host, port=srv.port)  # a slot again
            late.shutdown()
            rtr.recv(0.2)  # would raise CanError had the server answered the RTR with '< error ... >'
            rtr.shutdown()
            rude.close()
            stop.set()
            pump.join(2)
            deadline = time.monotonic() + 3.0
            while (len(got) < len(sent)) and time.monotonic() < deadline:
                msg = good.recv(0.2)
                if msg is None:
                    continue
                if msg.arbitration_id == 0x281:
                    got.append(int.from_bytes(msg.data, "little"))
                else:
                    other_ids.append((msg.arbitration_id, len(msg.data) == 0))
            assert got == sent  # every frame, in order, throughout
            assert (0x181, True) in other_ids  # the RTR frame, relayed
            assert 0.5 <= closed_after <= 2.5, closed_after
        finally:
            stop.set()
            good.shutdown()
            sender.shutdown()


def _frames_until(listener: can.BusABC, enough: Callable[[list[can.Message]], bool], what: str,
                  timeout_s: float = 10.0) -> list[can.Message]:
    """Frames ``listener`` heard until ``enough`` of them came; fails at the hang bound naming ``what``."""
    got: list[can.Message] = []
    deadline = time.monotonic() + timeout_s
    while not enough(got):
        msg = listener.recv(max(0.0, deadline - time.monotonic()))
        if msg is None:
            raise AssertionError(f"timed out after {timeout_s} s waiting for {what}; heard {len(got)} frames")
        got.append(msg)
    return got


def _median_period(stamps: list[float]) -> float:
    return statistics.median(b - a for a, b in itertools.pairwise(stamps))


def test_cyclic_jobs_add_update_delete_and_end_with_their_client(server: SocketcandServer) -> None:
    """socketcand's broadcast manager: '< add >' makes the server send a frame on its own timer.

    Judged by the frames' own bus stamps (each is its job's due time, or its arrival if the
    server was late) and by their order on the one wire, never by how many came in a time the
    test measured: a busy machine delays the test, not the bus's verdict."""
    listener = can.Bus(interface="socketcand", channel="can0", host=server.host, port=server.port)
    keeper = raw_client(server)  # another client's job: the ticks that prove the listener listens
    try:
        sock = raw_client(server)
        assert "< hi >" in read_until(sock, "< hi >")
        sock.sendall(b"< open can0 >")
        assert "< ok >" in read_until(sock, "< ok >")  # BCM mode: no rawmode needed
        sock.sendall(b"< add 0 10000 080 0 >< add 0 20000 123 2 AA BB >")
        got = _frames_until(listener, lambda got: sum(m.arbitration_id == 0x123 for m in got) >= 25,
                            "25 frames of the 20 ms job")
        syncs = [m.timestamp for m in got if m.arbitration_id == 0x080]
        other = [m for m in got if m.arbitration_id == 0x123]
        assert abs(_median_period(syncs) - 0.01) < 0.001, syncs  # each job's median period is its own
        assert abs(_median_period([m.timestamp for m in other]) - 0.02) < 0.001, [m.timestamp for m in other]
        assert {bytes(m.data) for m in other} == {b"\xaa\xbb"}
        # the delete goes before the update: no SYNC may follow the first frame with the new data
        sock.sendall(b"< delete 080 >< update 123 1 CC >")
        got = _frames_until(listener, lambda got: sum(bytes(m.data) == b"\xcc" for m in got) >= 5,
                            "5 frames of the updated job")
        first_cc = next(i for i, m in enumerate(got) if bytes(m.data) == b"\xcc")
        after = got[first_cc:]
        assert not [m for m in after if m.arbitration_id == 0x080], after
        assert {bytes(m.data) for m in after if m.arbitration_id == 0x123} == {b"\xcc"}, after
        sock.sendall(b"< add 0 0 200 0 >< delete 7FF >< add x 0 080 0 >")
        replies = read_until(sock, "out of range", 10.0)
        assert "cyclic period 0 s out of range" in replies, replies
        # the client goes: its job goes with it. Another client's 10 ms job keeps ticking; once the
        # table holds only that job, whatever was on its way is heard before a marker, and then ten
        # of the keeper's frames (five of the gone job's periods) come without the gone job's frame
        assert "< hi >" in read_until(keeper, "< hi >")
        keeper.sendall(b"< open can0 >< add 0 10000 700 0 >")
        _frames_until(listener, lambda got: any(m.arbitration_id == 0x700 for m in got), "the keeper's job")
        sock.close()
        wait_for(lambda: len(server.cyclic) == 1, 10.0, "the closed client's job to go")
        heard_before_marker(listener, server.engine)
        got = _frames_until(listener, lambda got: sum(m.arbitration_id == 0x700 for m in got) >= 10,
                            "10 frames of the keeper's job")
        assert not [m for m in got if m.arbitration_id == 0x123], got
    finally:
        keeper.close()
        listener.shutdown()


def test_a_client_with_a_cyclic_job_outlives_the_handshake_timeout() -> None:
    """A BCM-mode client (a driver's SYNC job) never sends rawmode: it is not an idle one."""
    with BusEngine() as engine, SocketcandServer(engine, port=0, handshake_timeout_s=0.2) as srv:
        listener = can.Bus(interface="socketcand", channel="can0", host=srv.host, port=srv.port)
        idle, job = raw_client(srv), raw_client(srv)
        try:
            for sock in (idle, job):
                read_until(sock, "< hi >")
                sock.sendall(b"< open can0 >")
                read_until(sock, "< ok >")
            job.sendall(b"< add 0 20000 080 0 >")
            time.sleep(0.5)
            assert idle.recv(64) == b""  # the idle one was closed
            drain(listener, 0.05)
            assert len([m for m in drain(listener, 0.2) if m.arbitration_id == 0x080]) >= 8
            # its job deleted (a driver closing), it is still no idle client: it is served until it closes
            # (the demo's end logged "no rawmode (nor a cyclic job)" for the driver's SYNC connection)
            job.sendall(b"< delete 080 >")
            time.sleep(0.5)  # the server's read loop looks more than once meanwhile
            job.sendall(b"< echo >")
            assert "< echo >" in read_until(job, "< echo >")
        finally:
            idle.close()
            job.close()
            listener.shutdown()


@pytest.mark.parametrize("how", ["default", "switched off", "not permitted"])
def test_the_cyclic_timer_is_a_real_time_process_where_the_os_allows_it(how: str) -> None:
    """`rovercan sim`'s broadcast-manager timer (the SYNC of a socketcand driver) is a process of
    its own, under SCHED_FIFO where it may: a timer among the simulated drives' threads woke
    0.5-2 ms late at p99 (benchmarks/stack_run.py: SYNC period error 1.2-2.4 ms at a listener,
    0.07-0.5 with it). The simulated drives' runner and the server's threads are real-time too
    (below the driver's priority). ROVERCAN_REALTIME=0 switches it off; without CAP_SYS_NICE they
    stay ordinary and the SYNC still runs."""
    if not hasattr(os, "sched_setscheduler"):
        pytest.skip("this OS has no SCHED_FIFO")
    command = [sys.executable, "-m", "rovercan", "sim", "--drives", "1", "--port", "0"]
    env = dict(os.environ)
    expected = realtime_allowed()
    if how == "switched off":
        env["ROVERCAN_REALTIME"] = "0"
        expected = False
    elif how == "not permitted":
        if shutil.which("setpriv") is None or not expected:
            pytest.skip("needs setpriv and the right to drop CAP_SYS_NICE (root)")
        command = ["setpriv", "--inh-caps=-sys_nice", "--bounding-set=-sys_nice", *command]
        expected = False
    proc = subprocess.Popen(command, cwd=REPO, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert proc.stdout is not None
        assert "simulated drive" in proc.stdout.readline()
        port = int(proc.stdout.readline().rsplit("port=", 1)[1])
        # the simulated drives' runner and the server's threads: real-time where allowed; no job, no timer process
        wait_for(lambda: (fifo_thread_count(proc.pid) >= 2) == expected, 30.0, "the simulator's threads' scheduling")
        assert fifo_thread_count(proc.pid, children=True) == fifo_thread_count(proc.pid)
        with can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=port) as listener:
            sock = socket.create_connection(("127.0.0.1", port), timeout=2.0)
            try:
                assert "< hi >" in read_until(sock, "< hi >")
                sock.sendall(b"< open can0 >")
                assert "< ok >" in read_until(sock, "< ok >")
                sock.sendall(b"< add 0 10000 080 0 >")
                syncs: list[can.Message] = []  # the SYNC runs either way: 20 of them heard, however late
                wait_for(lambda: bool(syncs.extend(m for m in drain(listener, 0.05) if m.arbitration_id == 0x080))
                         or len(syncs) >= 20, 30.0, "20 SYNCs of the timer")
                timer = fifo_thread_count(proc.pid, children=True) - fifo_thread_count(proc.pid)
                assert timer == int(expected)  # the timer process, beside the process's own
                assert expected or fifo_thread_count(proc.pid) == 0
            finally:
                sock.close()
    finally:
        proc.terminate()
        _, err = proc.communicate(timeout=30)
    # refused: said once, at start, for the runner and the server together
    assert err.count(f"SCHED_FIFO {SIM_PRIORITY} refused") == (how == "not permitted"), err


def test_a_frame_is_stamped_when_it_reached_the_server_not_when_read(server: SocketcandServer) -> None:
    """A frame's bus time is its arrival at the server (the kernel's stamp), as a CAN controller
    stamps a frame on the wire: an interpreter busy elsewhere does not make the client look late."""
    listener = can.Bus(interface="socketcand", channel="can0", host=server.host, port=server.port)
    sock = raw_client(server)
    try:
        assert read_until(sock, "< hi >").endswith("< hi >")
        sock.sendall(b"< open can0 >")
        assert "< ok >" in read_until(sock, "< ok >")
        sock.sendall(b"< rawmode >")
        assert "< ok >" in read_until(sock, "< ok >")
        old = sys.getswitchinterval()
        sys.setswitchinterval(1.0)  # the loop below keeps the interpreter from the server's reader
        try:
            sent = time.time()
            sock.sendall(b"< send 123 1 AA >")
            busy_until = time.monotonic() + 0.15
            while time.monotonic() < busy_until:
                pass
        finally:
            sys.setswitchinterval(old)
        msg = listener.recv(2.0)
        assert msg is not None and msg.arbitration_id == 0x123
        assert 0.0 <= msg.timestamp - sent < 0.05, f"stamped {msg.timestamp - sent:.4f} s after it was sent"
    finally:
        sock.close()
        listener.shutdown()


def test_frames_on_one_channel_are_stamped_in_time_order() -> None:
    """One wire, one order in time: a frame delivered after another is never stamped before it."""
    with BusEngine() as engine:
        channel = engine.channel("can0")
        seen: list[float] = []
        channel.attach(lambda msg: seen.append(msg.timestamp))
        channel.send(can.Message(arbitration_id=1, data=b"", timestamp=10.0))
        channel.send(can.Message(arbitration_id=2, data=b"", timestamp=5.0))
        channel.send(can.Message(arbitration_id=3, data=b""))
        assert seen[:2] == [10.0, 10.0] and seen[2] >= 10.0


def test_a_delayed_frame_is_stamped_when_it_reaches_the_wire() -> None:
    """The delay fault holds a frame back: its stamp is when it is delivered, not its arrival."""
    with BusEngine() as engine:
        channel = engine.channel("can0")
        seen: list[float] = []
        channel.attach(lambda msg: seen.append(msg.timestamp))
        channel.faults.delay, channel.faults.delay_s = 1.0, 0.05
        arrived = time.time()
        channel.send(can.Message(arbitration_id=1, data=b"", timestamp=arrived))
        deadline = time.monotonic() + 2.0
        while not seen and time.monotonic() < deadline:
            time.sleep(0.01)
        assert seen and seen[0] - arrived >= 0.04
