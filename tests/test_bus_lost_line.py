"""When the bus server goes away, the driver's log carries one line naming the bus and the cause,
and no traceback text from any thread (issues 52, 53: a SIGKILL of the simulator made six, from
python-can's receive error, its broadcast manager and the receive thread). A real `rovercan sim`
process is killed under a real driver process; everything the driver printed (every thread's
logging, and stderr, where Python prints an unhandled thread exception) is read."""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from motor_driver.process.jobs import brief_error

from .conftest import REPO, wait_for
from .test_sim_cli import free_port

DRIVER = """
import logging, sys, time
from can_config import load_config
from motor_driver import MotorDriver
logging.basicConfig(stream=sys.stderr, level=logging.INFO, format="%(threadName)s %(name)s %(levelname)s %(message)s")
with MotorDriver(load_config(sys.argv[1])).start() as driver:
    print("started", flush=True)
    sys.stdin.read()  # until the test closes it
"""


class Output:
    """A process's merged output, read by a thread as it comes."""

    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.lines: list[str] = []
        assert proc.stdout is not None
        self._thread = threading.Thread(target=lambda: self.lines.extend(iter(proc.stdout.readline, "")),  # type: ignore[union-attr]
                                        daemon=True)
        self._thread.start()

    def text(self) -> str:
        return "".join(self.lines)


@pytest.mark.parametrize("sync_timer", ["auto", "thread"])
def test_a_killed_server_is_one_line_naming_the_bus_and_the_cause(tmp_path: Path, sync_timer: str) -> None:
    port = free_port()
    config = tmp_path / "rover.yaml"
    config.write_text("buses: [{name: can0, interface: socketcand, channel: can0, sync_timer: " + sync_timer +
                      f", kwargs: {{host: 127.0.0.1, port: {port}}}}}]\n"
                      "drives: [{name: a, node_id: 1, counts_per_rev: 4096}, {name: b, node_id: 2, counts_per_rev: 4096}]\n")
    sim = subprocess.Popen([sys.executable, "-m", "rovercan", "sim", "--drives", "2", "--port", str(port)], cwd=REPO,
                           stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    driver = None
    try:
        assert sim.stdout is not None and "simulated drive" in sim.stdout.readline()
        driver = subprocess.Popen([sys.executable, "-c", DRIVER, str(config)], cwd=REPO, stdin=subprocess.PIPE,
                                  stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        out = Output(driver)
        wait_for(lambda: "started" in out.text(), 30.0, "the driver started", out.text)
        sim.send_signal(signal.SIGKILL)
        sim.wait(timeout=10)
        wait_for(lambda: "bus can0 lost" in out.text(), 10.0, "the loss said", out.text)
        # what follows the loss (the drop of the connection, the reconnect tries) has been said too
        wait_for(lambda: "reconnect failed" in out.text(), 10.0, "a reconnect tried", out.text)
    finally:
        if sim.poll() is None:
            sim.kill()
            sim.wait(timeout=10)
        if driver is not None:
            driver.communicate(input="", timeout=30)
    text = out.text()
    lost = [line for line in text.splitlines() if "lost (" in line and "bus can0" in line]
    assert len(lost) == 1, text
    assert "Traceback" not in text and "Exception in thread" not in text, text
    assert any(cause in lost[0] for cause in ("closed the connection", "receive failed", "sends fail")), lost


def test_brief_error_keeps_the_first_line_and_the_cause() -> None:
    """python-can's "Failed to receive: ... Traceback (most recent call last) ..." in one line."""
    try:
        try:
            raise ConnectionResetError(104, "Connection reset by peer")
        except ConnectionResetError as err:
            raise OSError("Failed to receive: [Errno 104] Connection reset by peer  Traceback (most recent call"
                          " last):\n  File \"x.py\", line 1\nConnectionResetError: [Errno 104]") from err
    except OSError as err:
        line = brief_error(err)
    assert "Traceback" not in line and "\n" not in line and line.startswith("Failed to receive"), line
