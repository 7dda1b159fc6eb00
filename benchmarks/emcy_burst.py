"""A babbling node's cost to the driver's receive thread: a burst of EMCY frames (0x2310 from
node 1) through every listener a bus's receive thread runs for a frame (canopen's dispatch into
the drive's cache, the bus statistics, the other-master watch, the flight recorder's tap), the
driver booted on the simulator, logging on (to /dev/null, as a node's log bridge would take it).
It reports the receive thread's CPU time per EMCY and the rate one core then keeps up with; a
real bus carries about 8,000 frames/s at 1 Mbit/s.

``--storm [SECONDS]`` (issue 73): the driver's memory under a babbling node's storm at the
emulator's full rate. The driver runs alone in a child process (``--drive``, booted on the
simulator this process serves); a raw socketcand client sends node 1's EMCY as fast as the server
takes it for SECONDS (10; about 345,000 frames). Figures: the child's resident memory (VmRSS, not
the peak VmHWM) before the storm, at its end and STORM_SETTLE_S after it, and a verdict: the
driver ends within STORM_RSS_MB of where it started (the flight recorder is bounded by count as
well as time, EMCY history and python-can's queues by theirs).

With ``--node`` the driver is the rover's ROS driver node (``python -m nodes.rover_driver`` on
the shipped config/rover.yaml, six drives on two buses, against ``rovercan sim --config`` of it), as
a rover runs it: rclpy and its publishers beside the same driver.

``python benchmarks/emcy_burst.py [FRAMES]`` prints the figures as JSON;
``python benchmarks/emcy_burst.py --storm [--node] [SECONDS]`` prints the storm's.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))
sys.path.insert(0, str(REPO / "benchmarks"))

import can  # noqa: E402

from can_config import RoverConfig, parse_config, with_bus_overrides  # noqa: E402
from motor_driver import MotorDriver  # noqa: E402
from virtual_can import SimService  # noqa: E402

EMCY = bytes([0x10, 0x23, 0x01, 0, 0, 0, 0, 0])


STORM_S = 10.0
STORM_SETTLE_S = 5.0
STORM_RSS_MB = 20.0
STORM_LINE = b"< send 081 8 10 23 01 00 00 00 00 00 >"
#: The node's start and its six drives' boot on the simulator, with room (no figure is taken before).
NODE_BOOT_S = 30.0


def bench_config() -> RoverConfig:
    return parse_config({"buses": [{"name": "can0", "interface": "socketcand", "channel": "can0",
                                      "kwargs": {"host": "127.0.0.1", "port": 1}}],
                           "drives": [{"name": f"joint{i}", "node_id": i, "host_timeout_ms": 500.0} for i in (1, 2)]},
                        source=REPO / "benchmarks" / "emcy_burst.yaml")


def burst(frames: int) -> dict[str, float]:
    config = bench_config()
    sim = SimService.from_config(config, port=0)
    driver = MotorDriver(with_bus_overrides(config, host=sim.host, port=sim.port)).start()
    try:
        listeners = driver.buses["can0"].network.listeners
        messages = [can.Message(arbitration_id=0x081, data=EMCY, is_extended_id=False, timestamp=time.time())
                    for _ in range(frames)]
        start = time.thread_time()
        for msg in messages:  # what python-can's Notifier does with each frame it received
            for listener in listeners:
                listener.on_message_received(msg)
        cpu_s = time.thread_time() - start
    finally:
        driver.close()
        sim.close()
    return {"emcy_frames": frames, "emcy_cpu_us": round(cpu_s / frames * 1e6, 2),
            "emcy_per_s_one_core": round(frames / cpu_s)}


def drive(host: str, port: int) -> None:
    """The child: the driver alone in its process, booted on the parent's simulator, until stdin closes."""
    driver = MotorDriver(with_bus_overrides(bench_config(), host=host, port=port)).start()
    try:
        print("ready", flush=True)
        sys.stdin.read()
    finally:
        driver.close()


def rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return round(int(line.split()[1]) / 1024, 1)
    raise KeyError("VmRSS")


def babble(host: str, port: int, seconds: float) -> int:
    """A raw socketcand client sending node 1's EMCY as fast as the server reads it for ``seconds``;
    returns how many frames the server took (it answers the closing echo once it read them all)."""
    sock = socket.create_connection((host, port), timeout=30.0)
    try:
        for line, reply in ((None, b"< hi >"), (b"< open can0 >", b"< ok >"), (b"< rawmode >", b"< ok >")):
            if line:
                sock.sendall(line)
            assert sock.recv(64).startswith(reply)
        batch, sent = STORM_LINE * 500, 0
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            sock.sendall(batch)
            sent += 500
        sock.sendall(b"< echo >")
        seen = b""
        while b"< echo >" not in seen:  # frames of the bus arrive too: read past them
            seen = seen[-16:] + sock.recv(65536)
        return sent
    finally:
        sock.close()


def storm(seconds: float = STORM_S, node: bool = False) -> dict[str, Any]:
    with ExitStack() as stack:
        incidents = stack.enter_context(tempfile.TemporaryDirectory())
        env = {**os.environ, "ROVERCAN_INCIDENT_DIR": incidents}  # the storm's incidents, not in the home directory
        if node:
            from stack_run import SHIPPED, on_port, simulator
            host, port = "127.0.0.1", stack.enter_context(simulator("--config", str(SHIPPED["rover"])))
            config = on_port(SHIPPED["rover"], port, stack.enter_context(tempfile.TemporaryDirectory()))
            env.setdefault("ROS_DOMAIN_ID", str(70 + os.getpid() % 30))  # /arm and /cmd_vel of its own
            child = subprocess.Popen([sys.executable, "-m", "nodes.rover_driver", "--ros-args", "-p", f"config:={config}"],
                                     cwd=REPO, env=env, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, text=True)
            boot_s = NODE_BOOT_S
        else:
            sim = stack.enter_context(SimService.from_config(bench_config(), port=0))
            host, port = sim.host, sim.port
            child = subprocess.Popen([sys.executable, __file__, "--drive", host, str(port)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env=env)
            assert child.stdout is not None and child.stdout.readline().strip() == "ready"
            boot_s = 2.0
        try:
            time.sleep(boot_s)  # booted: its heap settles before the first figure
            before = rss_mb(child.pid)
            started = time.monotonic()
            frames = babble(host, port, seconds)
            took_s = time.monotonic() - started
            end = rss_mb(child.pid)
            time.sleep(STORM_SETTLE_S)
            after = rss_mb(child.pid)
        finally:
            if child.stdin is not None:
                child.stdin.close()
            else:
                child.send_signal(signal.SIGINT)
            try:
                child.wait(30)
            except subprocess.TimeoutExpired:
                child.kill()
                child.wait()
    grown = round(after - before, 1)
    return {"driver": "nodes.rover_driver (config/rover.yaml)" if node else "MotorDriver (2 drives)",
            "storm_frames": frames, "storm_s": round(took_s, 1), "storm_frames_per_s": round(frames / took_s),
            "rss_before_mb": before, "rss_end_mb": end, f"rss_{STORM_SETTLE_S:g}s_after_mb": after,
            "rss_grown_mb": grown, "rss_bound_mb": STORM_RSS_MB,
            "verdict": "pass" if grown <= STORM_RSS_MB else f"FAIL: the driver kept {grown} MB after the storm"}


def main() -> int:
    with open("/dev/null", "w") as sink:
        logging.basicConfig(stream=sink, level=logging.INFO)
        if sys.argv[1:2] == ["--drive"]:
            drive(sys.argv[2], int(sys.argv[3]))
            return 0
        if sys.argv[1:2] == ["--storm"]:
            node = "--node" in sys.argv
            rest = [a for a in sys.argv[2:] if a != "--node"]
            figures = storm(float(rest[0]) if rest else STORM_S, node)
            print(json.dumps(figures, indent=1))
            return 0 if figures["verdict"] == "pass" else 1
        print(json.dumps(burst(int(sys.argv[1]) if len(sys.argv) > 1 else 10_000), indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
