"""The live view (issue 54): `rovercan monitor --config C --foxglove PORT` answers a WebSocket
client of subprotocol foxglove.websocket.v1 (the `websockets` library, not the project's code)
with serverInfo and an advertise of its channels, and sends a subscribed JointState as CDR."""

from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
import threading
from pathlib import Path
from typing import IO, Any

import pytest
import websockets

from can_config import load_config

from .conftest import REPO, rovercan_sim, wait_for
from .test_mcap import ROVER, rover_on_port
from .test_sim_cli import free_port

#: Bounds for hangs, not verdicts.
LISTEN_S = 120.0  # a launch of the nodes and a monitor on a crowded machine
ANSWER_S = 20.0
#: What a view says once it listens (``rovercan monitor`` on stderr, ``rovercan sim`` on stdout).
LISTENS = "Foxglove WebSocket on ws://"


class Said:
    """A process's output stream, read by a thread of its own into lines (the process never
    blocks on a full pipe), so that a test can wait for what it says."""

    def __init__(self, stream: IO[str] | None) -> None:
        assert stream is not None
        self.lines: list[str] = []
        self._thread = threading.Thread(target=self._read, args=(stream,), daemon=True, name="test-said")
        self._thread.start()

    def _read(self, stream: IO[str]) -> None:
        for line in stream:
            self.lines.append(line)

    def wait(self, text: str, what: str) -> None:
        wait_for(lambda: any(text in line for line in list(self.lines)), LISTEN_S, what, said=self.text)

    def text(self) -> str:
        self._thread.join(0.1)
        return "".join(self.lines)

    def close(self) -> str:
        """All it said, once the process has ended."""
        self._thread.join(30)
        return "".join(self.lines)


async def connect(port: int) -> Any:
    """A client of subprotocol foxglove.websocket.v1, of a view that said it listens (once: a
    refused connect is the test's failure, not a race with the server's start)."""
    return await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.websocket.v1"])


async def talk(port: int) -> tuple[dict[str, dict], bytes]:
    """serverInfo and advertise; then one message of /joint_states after subscribing to it."""
    async with await connect(port) as ws:
        assert ws.subprotocol == "foxglove.websocket.v1"
        got: dict[str, dict] = {}
        while "advertise" not in got or "serverInfo" not in got:
            message = json.loads(await asyncio.wait_for(ws.recv(), ANSWER_S))
            got[message["op"]] = message
        joint = next(c for c in got["advertise"]["channels"] if c["topic"] == "/joint_states")
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 7, "channelId": joint["id"]}]}))
        while True:
            data = await asyncio.wait_for(ws.recv(), ANSWER_S)
            if isinstance(data, bytes) and data[0] == 1:  # a message data frame
                return got, data


@pytest.mark.slow
def test_monitor_serves_foxglove_websocket(tmp_path: Path) -> None:
    port = free_port()
    with rovercan_sim("--config", str(ROVER)) as sim_port:
        config = rover_on_port(tmp_path, sim_port)
        mon = subprocess.Popen([sys.executable, "-m", "rovercan", "monitor", "--config", str(config), "--foxglove",
                                str(port)], cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        said = Said(mon.stderr)
        jog = None
        try:
            jog = subprocess.Popen([sys.executable, "-m", "rovercan", "jog", "wheel_front_left", "30", "--for", "20",
                                    "--config", str(config)], cwd=REPO, stdout=subprocess.DEVNULL,
                                   stderr=subprocess.DEVNULL)
            said.wait(LISTENS, "the monitor's view to listen")
            got, data = asyncio.run(talk(port))
        finally:
            if jog is not None:
                jog.send_signal(signal.SIGINT)
                jog.wait(timeout=30)
            mon.send_signal(signal.SIGINT)
            mon.wait(timeout=30)
            err = said.close()
    assert mon.returncode == 0, err
    assert got["serverInfo"]["name"] == "rovercan"
    channels = {c["topic"]: c for c in got["advertise"]["channels"]}
    drives = [d.name for d in load_config(ROVER).drives]
    assert {"/can/frames", "/joint_states", "/diagnostics", *(f"/drives/{d}/status" for d in drives)} <= set(channels)
    joint = channels["/joint_states"]
    assert (joint["encoding"], joint["schemaName"], joint["schemaEncoding"]) == ("cdr", "sensor_msgs/msg/JointState",
                                                                                  "ros2msg")
    assert int.from_bytes(data[1:5], "little") == 7  # our subscription's message
    assert b"wheel_front_left" in data[13:]  # CDR of a JointState naming the drives


def test_foxglove_port_in_use_is_a_clear_error(tmp_path: Path) -> None:
    import socket

    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        done = subprocess.run([sys.executable, "-m", "rovercan", "monitor", "-i", "virtual", "-c", "foxglove-test",
                               "--foxglove", str(port), "--seconds", "1"], cwd=REPO, capture_output=True, text=True,
                              timeout=60)
    assert done.returncode == 2, done.stderr
    assert f"--foxglove {port}: cannot serve on 127.0.0.1:{port}" in done.stderr
