"""Everything the driver's process says goes through the ROS log: a run of rover_driver on the
simulator in which a drive is unplugged (it is declared lost, told to stop by RPDO, NMT and an SDO
that times out and is aborted), then SIGINT, writes no line to stdout or stderr that is not an
rcutils log line (the canopen library's "Transfer aborted by client ...", a node module's own
logger, Python's last-resort handler and a thread's traceback would each be one)."""

from __future__ import annotations

import logging
import os
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from virtual_can import SimDriveSpec, SimService
from virtual_can.scenario import apply_action

from .conftest import REPO, in_thread, requires_ros, wait_for

pytestmark = requires_ros

#: rcutils' console format: "[SEVERITY] [seconds.nanoseconds] [logger]: message".
ROS_LINE = re.compile(r"^\[(DEBUG|INFO|WARN|ERROR|FATAL)\] \[\d+\.\d+\] \[[\w./-]+\]: ")
#: The traceback a log line carries, after it (the bridge puts it in the line's text).
TRACEBACK_LINE = re.compile(r"^(Traceback \(most recent call last\):|  |\S*Boom: in a thread$)")


def test_a_run_with_a_lost_drive_writes_nothing_outside_the_log(tmp_path: Path) -> None:
    with SimService([SimDriveSpec(1), SimDriveSpec(2)], port=0) as sim:
        config = tmp_path / "rover.yaml"
        config.write_text("buses:\n  - {name: can0, interface: socketcand, channel: can0,"
                          f" kwargs: {{host: 127.0.0.1, port: {sim.port}}}}}\n"
                          "drives:\n" + "".join(f"  - {{name: {'ab'[n - 1]}, node_id: {n}, host_timeout_ms: 500,"
                                                 " heartbeat_timeout_ms: 1000}\n" for n in (1, 2)))
        env = dict(os.environ, RCUTILS_COLORIZED_OUTPUT="0", PYTHONUNBUFFERED="1")
        proc = subprocess.Popen([sys.executable, "-m", "nodes.rover_driver", "--ros-args", "-p", f"config:={config}",
                                 "-p", "arm:=true"], cwd=REPO, env=env, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        assert proc.stdout is not None and proc.stderr is not None
        out: list[str] = []
        err: list[str] = []
        readers = [in_thread(lambda stream=stream, into=into: into.extend(stream), name="test-output")[0]
                   for stream, into in ((proc.stdout, out), (proc.stderr, err))]

        def said() -> str:
            return "".join(out + err)

        try:
            runner = sim.simulator_for(2)
            wait_for(lambda: runner.call(lambda: runner.drive(2).state.name) == "OPERATION_ENABLED", 60.0,
                     "drive 2 enabled", said)
            apply_action(sim, {"action": "unplug", "node": 2})
            wait_for(lambda: "quick stop by SDO to the lost drive" in said(), 60.0,
                     "the lost drive told to stop by SDO (which times out)", said)
            proc.send_signal(signal.SIGINT)
            proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                proc.kill()
            for reader in readers:
                reader.join(10.0)
    assert "heartbeat lost" in said()
    # canopen's abort of this driver's own SDO transfer (the lost drive's stop timing out) is DEBUG,
    # below the node's INFO (motor_driver/bus/library_log.py): the driver's own lines say it
    assert "Transfer aborted by client" not in said()
    outside = [line for line in out + err if not ROS_LINE.match(line)]
    assert not outside, "".join(outside)


def test_a_node_modules_line_and_canopens_go_through_the_ros_log(capfd: pytest.CaptureFixture[str]) -> None:
    import rclpy

    from nodes.process.logbridge import bridge_core_logging, unbridge

    # an in-process CLI run earlier in this worker may have quieted canopen's logger (its
    # --verbose 0); what is tested is the bridge, so the logger passes its records here
    canopen_log = logging.getLogger("canopen.sdo.client")
    level = canopen_log.level
    canopen_log.setLevel(logging.NOTSET)
    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("log_check", context=context)
    handler = bridge_core_logging(node)
    try:
        logging.getLogger("nodes.actions.driver_actions").warning("goal for unknown joint %r refused; joints: %s", "wheel_x", ["a"])
        logging.getLogger("nodes.rover.drive_system").warning("drive system: %s left out, its quick stop failed (%s)", "b",
                                                        "timeout")
        logging.getLogger("canopen.sdo.client").error("Block transfer was not finished")  # canopen's ERROR
        thread = threading.Thread(target=boom, name="test-boom")
        thread.start()
        thread.join(10.0)
    finally:
        unbridge(handler)
        node.destroy_node()
        rclpy.shutdown(context=context)
        canopen_log.setLevel(level)
    out, err = capfd.readouterr()
    lines = (out + err).splitlines(keepends=True)
    for text in ("goal for unknown joint 'wheel_x' refused", "drive system: b left out",
                 "Block transfer was not finished", "thread test-boom ended: Boom: in a thread"):
        assert any(text in line and ROS_LINE.match(line) for line in lines), (text, lines)
    outside = [line for line in lines if not ROS_LINE.match(line) and not TRACEBACK_LINE.match(line)]
    assert not outside, "".join(outside)


class Boom(Exception):
    """An exception of a type no code names."""


def boom() -> None:
    raise Boom("in a thread")
