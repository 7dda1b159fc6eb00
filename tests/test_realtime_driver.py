"""A real-time driver's process (every thread under SCHED_FIFO: nodes/runtime.go_realtime) starts
its flight recorder's plot helper ordinary: matplotlib at real-time priority would take a core
from the driver's own threads for a second or two, at an incident, when they matter most."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from .conftest import REPO, realtime_allowed

SCRIPT = """
import os, sys, threading
from pathlib import Path
from can_config.config import RecorderConfig
from can_config.realtime import make_process_realtime
from motor_driver.recorder import FlightRecorder

assert make_process_realtime("test", 10)
recorder = FlightRecorder(RecorderConfig(dir=Path(sys.argv[1]).parent, plot=True), {"wheel": ("can0", 1)},
                          {"can0": "can0"})
after = []

def writer():  # as the recorder's writer thread: real-time again once the helper is started
    recorder._plot_in_helper(Path(sys.argv[1]))
    after.append(os.sched_getscheduler(0))

thread = threading.Thread(target=writer)
thread.start()
thread.join()
print("writer policy after", after[0])
helper = recorder._helpers[-1]
stat = Path(f"/proc/{helper.pid}/stat").read_text()  # it waits to open the FIFO: alive
print("helper policy", int(stat.rsplit(")", 1)[1].split()[38]))
print("own policy", os.sched_getscheduler(0))
helper.kill()
helper.wait()
recorder.close()
"""


def test_the_plot_helper_of_a_real_time_driver_runs_ordinary(tmp_path: Path) -> None:
    if not hasattr(os, "mkfifo") or not realtime_allowed():
        pytest.skip("needs SCHED_FIFO (root, CAP_SYS_NICE or an rtprio limit) and FIFOs")
    incident = tmp_path / "incident.json"
    os.mkfifo(incident)  # the helper blocks opening it, so its scheduling can be read while it lives
    out = subprocess.run([sys.executable, "-c", SCRIPT, str(incident)], cwd=REPO, capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert f"helper policy {os.SCHED_OTHER}" in out.stdout, out.stdout
    assert f"own policy {os.SCHED_FIFO}" in out.stdout, out.stdout  # the driver's main thread stays real-time
    assert f"writer policy after {os.SCHED_FIFO}" in out.stdout, out.stdout  # and the writer, once the helper is out
