"""A real-time driver's process (its threads under SCHED_FIFO: nodes/process/spinning.go_realtime) starts
its flight recorder's plot helper ordinary: matplotlib at real-time priority would take a core
from the driver's own threads for a second or two, at an incident, when they matter most. Its
buses' receive threads run real-time like the rest, on first connect and on every reconnect: an
ordinary one holding the interpreter was preempted there by real-time work, and every other
thread of the driver waited for it (motor_driver/bus/handle.py)."""

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
from motor_driver.recording.flight import FlightRecorder

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


RECEIVE_SCRIPT = """
import os, sys, threading
from can_config import parse_config
from can_config.realtime import make_process_realtime
from motor_driver import MotorDriver
from motor_driver.bus.connect import open_bus

def receive_policies():
    return sorted((os.sched_getscheduler(t.native_id), os.sched_getparam(t.native_id).sched_priority)
                  for t in threading.enumerate() if t.name.startswith("Notifier for bus") and t.is_alive())

assert make_process_realtime("test", 10)
config = parse_config({"buses": [{"name": "can0", "interface": "socketcand", "channel": "can0",
                                  "kwargs": {"host": "127.0.0.1", "port": int(sys.argv[1])}}],
                       "drives": [{"name": "a", "node_id": 1}]})
with MotorDriver(config) as driver:
    print("connected", receive_policies())
    handle = driver._handles["can0"]
    # on the bus's worker, as the supervisor's reconnect runs (motor_driver/runtime/supervise_bus.py)
    def again():
        handle.disconnect()
        handle.reconnect(open_bus(config.bus("can0").bus_kwargs()))
        return os.sched_getscheduler(0)
    print("worker policy", handle.worker.submit(again).result(timeout=60))
    print("reconnected", receive_policies())
    print("own policy", os.sched_getscheduler(0))
"""


def test_a_real_time_drivers_receive_threads_run_real_time_after_connect_and_reconnect() -> None:
    if not realtime_allowed():
        pytest.skip("needs SCHED_FIFO (root, CAP_SYS_NICE or an rtprio limit)")
    from virtual_can.service import SimDriveSpec, SimService

    with SimService([SimDriveSpec(1)], port=0) as sim:
        out = subprocess.run([sys.executable, "-c", RECEIVE_SCRIPT, str(sim.port)], cwd=REPO, capture_output=True,
                             text=True, timeout=120)
    assert out.returncode == 0, out.stderr[-2000:]
    assert f"connected [({os.SCHED_FIFO}, 10)]" in out.stdout, out.stdout  # the process's priority
    assert f"reconnected [({os.SCHED_FIFO}, 10)]" in out.stdout, out.stdout  # the old thread gone, the new one real-time
    assert f"worker policy {os.SCHED_FIFO}" in out.stdout, out.stdout
    assert f"own policy {os.SCHED_FIFO}" in out.stdout, out.stdout  # the thread that started them stays real-time
