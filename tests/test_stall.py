"""A driver process stalled (SIGSTOP, then SIGCONT: a starved or paused process) stops hearing its
drives while they stop themselves (their host watch). On waking it judges their heartbeats by
how far its receive thread has read on the bus's own time line (tests/test_read_behind.py), so
the heartbeats waiting in its socket are read before any drive is judged lost; where it did
tell one to stop (an older driver did, to all of them), that was its own doing (issue 53). Either
way nothing says "another master", and /arm arms the rover again. The real processes: the ROS driver node (and
the lifecycle node, configured, activated and armed at start) as subprocesses, the simulator in this
one; the stall lasts until the simulated drives have stopped themselves (a condition, not a
clock)."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import can
import pytest

from can_config import GENERIC_EDS
from virtual_can import SimService
from virtual_can.service import SimDriveSpec

from .conftest import IN_PROCESS_HOST_TIMEOUT_MS, REPO, requires_ros, ros_probe, wait_for

#: Heartbeats (100 ms apart) of a drive the stalled driver does not read: 0.8 s, past its 300 ms timeout.
STALL_HEARTBEATS = 8
ENTRY_POINTS = {"rover_driver": ["nodes.rover_driver"],
                "lifecycle": ["nodes.rover_lifecycle"]}


def sim_states(sim: SimService) -> list[str]:
    runner = sim.simulators["can0"]
    return [str(runner.call(lambda n=n: runner.drive(n).state.name)) for n in (1, 2)]


class Output:
    def __init__(self, proc: subprocess.Popen[str]) -> None:
        self.lines: list[str] = []
        stream = proc.stdout
        assert stream is not None
        threading.Thread(target=lambda: self.lines.extend(iter(stream.readline, "")), daemon=True).start()

    def text(self) -> str:
        return "".join(self.lines)


def arm(probe: Any, executor: Any) -> tuple[bool, str]:
    from std_srvs.srv import Trigger

    client = probe.create_client(Trigger, "/arm")
    try:
        assert client.wait_for_service(timeout_sec=30.0), "no /arm"
        future = client.call_async(Trigger.Request())
        executor.spin_until_future_complete(future, timeout_sec=30.0)
        reply = future.result()
        assert reply is not None, "/arm did not answer"
        return bool(reply.success), str(reply.message)
    finally:
        probe.destroy_client(client)


def armed(probe: Any, executor: Any, within_s: float = 30.0) -> tuple[bool, str]:
    """/arm until it succeeds (a bound for a hang, not a verdict); its last answer."""
    deadline = time.monotonic() + within_s
    while not (answer := arm(probe, executor))[0] and time.monotonic() < deadline:
        executor.spin_once(timeout_sec=0.2)
    return answer


@requires_ros
@pytest.mark.parametrize("entry", sorted(ENTRY_POINTS))
def test_a_stalled_driver_process_is_no_other_master_and_arms_again(tmp_path: Path, entry: str) -> None:
    import rclpy

    specs = [SimDriveSpec(n, GENERIC_EDS, "can0", name, 4096) for n, name in ((1, "a"), (2, "b"))]
    with SimService(specs, port=0) as sim:
        config = tmp_path / "rover.yaml"
        # the drives' host consumer time as in the in-process rigs: at 150 ms a driver starved beside
        # the suite after the re-arm had them stop themselves again (the stall outlasts any bound)
        watch = f"heartbeat_period_ms: 100, heartbeat_timeout_ms: 300, host_timeout_ms: {IN_PROCESS_HOST_TIMEOUT_MS:g}"
        config.write_text("buses: [{name: can0, interface: socketcand, channel: can0,"
                          f" kwargs: {{host: 127.0.0.1, port: {sim.port}}}}}]\n"
                          f"drives: [{{name: a, node_id: 1, counts_per_rev: 4096, {watch}}},"
                          f" {{name: b, node_id: 2, counts_per_rev: 4096, {watch}}}]\n")
        args = ["--ros-args", "-p", f"config:={config}"] + (["-p", "autostart:=true", "-p", "arm:=true"] if entry == "lifecycle" else [])
        proc = subprocess.Popen([sys.executable, "-m", *ENTRY_POINTS[entry], *args], cwd=REPO,
                                env=dict(os.environ, ROS_AUTOMATIC_DISCOVERY_RANGE="LOCALHOST"),
                                stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        out = Output(proc)
        context, probe, executor = ros_probe("stall_probe")
        try:
            if entry != "lifecycle":  # the lifecycle node's autostart with arm arms them itself
                answer = armed(probe, executor)
                assert answer[0], (answer, out.text()[-3000:])
            wait_for(lambda: sim_states(sim) == ["OPERATION_ENABLED"] * 2, 30.0, "armed", out.text)
            listener = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
            proc.send_signal(signal.SIGSTOP)
            try:  # stalled until the drives have stopped themselves (their host watch saw the silence) and
                # have sent more heartbeats than the driver's heartbeat timeout allows: it finds them late
                wait_for(lambda: "OPERATION_ENABLED" not in sim_states(sim), 10.0, "the drives stopping themselves",
                         out.text)
                heartbeats = 0
                while heartbeats < STALL_HEARTBEATS:
                    msg = listener.recv(5.0)
                    assert msg is not None, "the simulated drive fell silent"
                    heartbeats += msg.arbitration_id == 0x701
            finally:
                proc.send_signal(signal.SIGCONT)
                listener.shutdown()
            answer = armed(probe, executor)  # refused while the drives are configured again
            assert answer[0], (answer, out.text()[-4000:])
            wait_for(lambda: sim_states(sim) == ["OPERATION_ENABLED"] * 2, 10.0, "armed again", out.text)
        finally:
            probe.destroy_node()
            rclpy.shutdown(context=context)
            if proc.poll() is None:
                proc.send_signal(signal.SIGTERM)
            proc.wait(timeout=30)
        text = out.text()
        assert "another master" not in text, text[-4000:]
        assert "Traceback" not in text, text[-4000:]
