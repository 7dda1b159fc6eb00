"""A drive that answers SDO requests wrongly cannot hang, fool or crash the driver: every SDO read
is bounded in size and time, every malformed answer is an SdoError of the project's tree, and a
boot against such a drive ends with a BootError naming its step.

The hostile drive is a program on the bus (a python-can client of the bus server), not the
simulator: it answers the NMT reset with a boot-up, sends heartbeats, and answers each SDO
request in the way a test asks for."""

from __future__ import annotations

import logging
import struct
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator

import can
import canopen
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from can_config import RoverConfig, parse_config, with_bus_overrides
from can_config.errors import BootError, MotorError, SdoError, SdoTimeoutError
from motor_driver import MotorDriver
from motor_driver.bus.sdo_client import OwnAnswersNode
from motor_driver.drive import SDO_TRANSFER_TIMEOUTS, SDO_UPLOAD_MAX_BYTES
from motor_driver.drive.sdo import SdoPort
from virtual_can import BusEngine, SimService, SocketcandServer
from virtual_can.server import RAWMODE_HOLD_S

from .conftest import REPO, make_config, wait_for

NODE = 5
SDO_TIMEOUT_S = 0.2


class HostileDrive:
    """Node 5 on the bus: boots when reset, beats, and answers SDO requests by ``answer``."""

    def __init__(self, port: int, answer: str) -> None:
        self.answer = answer
        self.bus = can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=port)
        self.stop = threading.Event()
        self.requests = 0
        self.aborts = 0  # of the requests: the client's aborts (0x80)
        self.stale_sent = False
        self.thread = threading.Thread(target=self.run, daemon=True)
        self.thread.start()
        time.sleep(RAWMODE_HOLD_S + 0.02)

    def send(self, cob: int, data: bytes) -> None:
        self.bus.send(can.Message(arbitration_id=cob, data=data, is_extended_id=False))

    def run(self) -> None:
        next_beat = 0.0
        while not self.stop.is_set():
            if time.monotonic() >= next_beat:
                self.send(0x700 + NODE, b"\x7f")
                next_beat = time.monotonic() + 0.1
            msg = self.bus.recv(0.02)
            if msg is None:
                continue
            if msg.arbitration_id == 0 and len(msg.data) == 2 and msg.data[1] in (0, NODE):
                self.send(0x700 + NODE, b"\x00")  # boot-up
            elif msg.arbitration_id == 0x600 + NODE:
                self.requests += 1
                self.aborts += msg.data[0] == 0x80
                self.reply(bytes(msg.data))

    def reply(self, req: bytes) -> None:
        cmd, index, sub = req[0], req[1:3], req[3:4]
        kind = self.answer
        if kind == "silence":
            return
        if kind in ("others first", "toggle once"):
            (self.reply_others_first if kind == "others first" else self.reply_toggle_once)(cmd, index, sub)
            return
        if kind == "short":
            self.send(0x580 + NODE, b"\x43")
        elif kind.startswith("bytes "):  # an expedited answer of n bytes (n = 0, 1 or 3)
            n = int(kind.split()[1])
            head = 0x42 if n == 0 else 0x43 | (4 - n) << 2
            self.send(0x580 + NODE, bytes([head]) + index + sub + b"\x07" * n)
        elif kind == "wrong index":
            self.send(0x580 + NODE, bytes([0x43]) + struct.pack("<H", 0x1234) + sub + b"\x01\x02\x03\x04")
        elif kind == "unknown abort":
            self.send(0x580 + NODE, bytes([0x80]) + index + sub + struct.pack("<I", 0x12345678))
        elif cmd & 0xE0 == 0x40:  # an upload initiate
            if kind == "huge size":
                self.send(0x580 + NODE, bytes([0x41]) + index + sub + struct.pack("<I", 0xFFFFFF00))
            else:  # endless: segmented, no size given, and the segments never end
                self.send(0x580 + NODE, bytes([0x40]) + index + sub + b"\x00\x00\x00\x00")
        elif cmd & 0xE0 == 0x60:  # a segment request: answer with its toggle, never the last
            toggle = cmd & 0x10
            if kind == "wrong toggle":
                toggle ^= 0x10
            self.send(0x580 + NODE, bytes([toggle]) + b"\x11" * 7)
        elif cmd & 0xE0 == 0x20:  # a download: acknowledged
            self.send(0x580 + NODE, bytes([0x60]) + index + sub + b"\x00" * 4)

    def reply_others_first(self, cmd: int, index: bytes, sub: bytes) -> None:
        """Each initiate gets, before its own answer, what a second client's transfers or a late
        answer to an earlier request look like on the shared COB-ID: an abort of another object,
        an upload answer about another object and a download answer about another object."""
        if cmd & 0xE0 not in (0x20, 0x40):
            return  # the client's abort: no answer
        self.send(0x580 + NODE, bytes([0x80]) + struct.pack("<H", 0x6061) + b"\x00" + struct.pack("<I", 0x06020000))
        self.send(0x580 + NODE, bytes([0x43]) + struct.pack("<H", 0x1018) + b"\x01" + b"\x9a\x00\x00\x00")
        self.send(0x580 + NODE, bytes([0x60]) + struct.pack("<H", 0x1017) + b"\x00" + b"\x00" * 4)
        if cmd & 0xE0 == 0x40:
            self.send(0x580 + NODE, bytes([0x43]) + index + sub + struct.pack("<I", 0x00020192))
        else:
            self.send(0x580 + NODE, bytes([0x60]) + index + sub + b"\x00" * 4)

    def reply_toggle_once(self, cmd: int, index: bytes, sub: bytes) -> None:
        """A segmented upload of b"abc" whose first segment answer has the wrong toggle, once
        (a segment of another transfer: no multiplexer tells it apart); then honest."""
        if cmd & 0xE0 == 0x40:
            self.send(0x580 + NODE, bytes([0x41]) + index + sub + struct.pack("<I", 3))
        elif cmd & 0xE0 == 0x60:
            toggle = cmd & 0x10
            if not self.stale_sent:
                self.stale_sent = True
                toggle ^= 0x10
            self.send(0x580 + NODE, bytes([toggle | 0x09]) + b"abc" + b"\x00" * 4)  # 3 bytes, the last segment

    def close(self) -> None:
        self.stop.set()
        self.thread.join()
        self.bus.shutdown()


@pytest.fixture
def server() -> Iterator[SocketcandServer]:
    with BusEngine() as engine, SocketcandServer(engine, port=0, channels=("can0",)) as srv:
        yield srv


def config(port: int):  # type: ignore[no-untyped-def]
    cfg = parse_config({"buses": [{"name": "can0", "interface": "socketcand", "channel": "can0"}],
                        "drives": [{"name": "hostile", "node_id": NODE, "counts_per_rev": 4096,
                                    "sdo_timeout_ms": SDO_TIMEOUT_S * 1000, "boot_timeout_ms": 1000}]})
    return with_bus_overrides(cfg, host="127.0.0.1", port=port)


#: How long one SDO read may take at most: the transfer's bound, plus the initiate's and the
#: last segment's request (each sent twice by canopen before it gives up).
READ_BOUND_S = (SDO_TRANSFER_TIMEOUTS + 4) * SDO_TIMEOUT_S + 0.5

KINDS = ["endless", "huge size", "short", "wrong index", "wrong toggle", "unknown abort", "silence"]


@pytest.mark.parametrize("kind", KINDS)
def test_each_malformed_answer_is_an_sdo_error_within_its_bound(server: SocketcandServer, kind: str) -> None:
    drive_bus = HostileDrive(server.port, kind)
    try:
        with MotorDriver(config(server.port)) as driver:
            drive = driver.drive("hostile")  # not started: one SDO read at a time
            for index, sub in ((0x1000, 0), (0x1008, 0), (0x6064, 0)):  # a U32, a string, an I32
                start = time.monotonic()
                with pytest.raises(SdoError) as err:
                    drive.sdo_read(index, sub)
                took = time.monotonic() - start
                assert took < READ_BOUND_S, (kind, index, took)
                if kind == "silence":
                    assert isinstance(err.value, SdoTimeoutError)
                if kind == "unknown abort":
                    assert err.value.abort_code == 0x12345678 and "0x12345678" in str(err.value)
    finally:
        drive_bus.close()


@pytest.mark.parametrize("what", ["read", "write"])
def test_answers_to_other_requests_are_dropped_and_the_own_one_taken(server: SocketcandServer, what: str,
                                                                    caplog: pytest.LogCaptureFixture) -> None:
    """Two clients of one node share its SDO answer COB-ID (a bench read beside the booting
    driver took the driver's "object does not exist" abort for its own and failed), and a late
    answer to an earlier request comes on it too: each answer that names another object, or is
    of another kind, is dropped, and the transfer's own answer is taken, with no retry."""
    caplog.set_level(logging.INFO, logger="motor_driver.bus.sdo_client")
    drive_bus = HostileDrive(server.port, "others first")
    try:
        with MotorDriver(config(server.port)) as driver:
            sdo = driver.drive("hostile").sdo
            if what == "read":
                assert sdo.read(0x1000, 0) == struct.pack("<I", 0x00020192)
            else:
                sdo.write(0x6060, 0, b"\x01")
            assert drive_bus.requests == 1 and drive_bus.aborts == 0  # its own answer, the first time
    finally:
        drive_bus.close()
    assert "an abort of 0x6061:0, not of" in caplog.text
    assert "it answers 0x1018:1, not 0x1000:0" in caplog.text if what == "read" else "not the 0x60" in caplog.text
    assert "trying once more" not in caplog.text


def test_a_segment_of_another_transfer_gets_the_transfer_tried_once_more(server: SocketcandServer,
                                                                         caplog: pytest.LogCaptureFixture) -> None:
    """A segment answer carries no object: one with the wrong toggle (another transfer's) makes
    canopen abort, and the transfer is tried once more, which the drive answers."""
    caplog.set_level(logging.INFO, logger="motor_driver.drive.sdo")
    drive_bus = HostileDrive(server.port, "toggle once")
    try:
        with MotorDriver(config(server.port)) as driver:
            assert driver.drive("hostile").sdo.read(0x1008, 0) == b"abc"
            assert drive_bus.aborts == 1 and drive_bus.stale_sent  # the crossed transfer, aborted once
    finally:
        drive_bus.close()
    assert "an answer not to this request" in caplog.text and "trying once more" in caplog.text


@pytest.mark.parametrize("kind", ["endless", "huge size"])
def test_a_boot_against_an_endless_or_oversized_upload_ends_with_a_boot_error(server: SocketcandServer,
                                                                            kind: str) -> None:
    drive_bus = HostileDrive(server.port, kind)
    try:
        start = time.monotonic()
        with MotorDriver(config(server.port)) as driver, pytest.raises(BootError) as err:
            driver.start()
        took = time.monotonic() - start
        assert err.value.step == "device type" and "0x1000" in str(err.value), err.value
        assert took < 0.5 + 1.0 + READ_BOUND_S, took  # the look, the boot-up wait, one bounded read
        assert drive_bus.requests < 10  # cut off: not the 58,855 frames of an unbounded read
    finally:
        drive_bus.close()


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(answer=st.binary(min_size=0, max_size=8))
def test_fuzzed_answers_never_raise_outside_the_tree(server: SocketcandServer, answer: bytes) -> None:
    """Whatever one answer frame holds, a read ends with a value or an error of the tree."""
    bus = can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=server.port)
    stop = threading.Event()

    def respond() -> None:
        while not stop.is_set():
            msg = bus.recv(0.02)
            if msg is not None and msg.arbitration_id == 0x600 + NODE:
                bus.send(can.Message(arbitration_id=0x580 + NODE, data=answer, is_extended_id=False))

    thread = threading.Thread(target=respond, daemon=True)
    thread.start()
    time.sleep(RAWMODE_HOLD_S + 0.02)
    try:
        with MotorDriver(config(server.port)) as driver:
            drive = driver.drive("hostile")
            start = time.monotonic()
            try:
                drive.sdo_read(0x1008, 0)
            except MotorError:
                pass
            assert time.monotonic() - start < READ_BOUND_S
    finally:
        stop.set()
        thread.join()
        bus.shutdown()


def bench(port: int, *args: str) -> subprocess.CompletedProcess[str]:
    """A bench command against the hostile node; the subprocess timeout is the hang detector."""
    return subprocess.run([sys.executable, "-m", "rovercan", *args, "-i", "socketcand", "-c", "can0", "--bus-kwargs",
                           "host=127.0.0.1", f"port={port}"], cwd=REPO, capture_output=True, text=True, timeout=60,
                          check=False)


@pytest.mark.parametrize("kind", ["endless", "huge size", "bytes 0", "bytes 1", "bytes 3"])
@pytest.mark.parametrize("command", [("sdo", "read", str(NODE), "0x1000"), ("sdo", "read", str(NODE), "0x1008"),
                                     ("info", str(NODE))])
def test_the_bench_reads_through_the_bounded_port(server: SocketcandServer, kind: str, command: tuple[str, ...]) -> None:
    """The bench's SDO reads are the driver's: an endless segmented upload is cut off (the landed
    bench was still reading at 60 s) and a short answer is one line, never a struct.error."""
    drive_bus = HostileDrive(server.port, kind)
    try:
        result = bench(server.port, *command, "--json")
    finally:
        drive_bus.close()
    assert "Traceback" not in result.stderr and "struct.error" not in result.stderr, result.stderr
    lines = [line for line in result.stderr.splitlines() if line.startswith("rovercan:")]
    assert result.returncode == 0 or (result.returncode == 1 and len(lines) == 1), (result.returncode, result.stderr)
    # cut off by size (SDO_UPLOAD_MAX_BYTES without an EDS: about 150 segments for one read, a few
    # reads for info), not the tens of thousands of frames of an unbounded read
    assert drive_bus.requests < 3 * (SDO_UPLOAD_MAX_BYTES // 7 + 10), drive_bus.requests


def test_a_second_client_beside_the_driver_gets_its_own_answers(
        driver_factory: Callable[[RoverConfig], tuple[SimService, MotorDriver]]) -> None:
    """The driver and a bench tool on one node at once (the two-bus test's SDO read failed with
    the driver's "object does not exist"): the driver reads an object the drive lacks, over and
    over, while the tool reads 0x6064; every one of the tool's reads is its own answer."""
    sim, driver = driver_factory(make_config(1))
    stop, aborts = threading.Event(), [0]

    def driver_reads_a_missing_object() -> None:
        while not stop.is_set():
            aborts[0] += driver.drive("joint1").sdo.read_optional(0x2FFF, 0) is None

    bus = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
    network = canopen.Network(bus)
    network.connect()
    node = OwnAnswersNode(1, driver.drive("joint1").od)
    network.add_node(node)
    tool = SdoPort("bench", node, node.object_dictionary, 1.0)
    thread = threading.Thread(target=driver_reads_a_missing_object, daemon=True)
    thread.start()
    try:
        wait_for(lambda: aborts[0] > 0, 30, "the driver's first abort")
        for _ in range(100):
            assert len(tool.read(0x6064, 0)) == 4
        assert aborts[0] > 10  # the aborts went on beside the tool's reads
    finally:
        stop.set()
        thread.join()
        network.disconnect()
