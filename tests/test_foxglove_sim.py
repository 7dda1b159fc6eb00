"""`--foxglove PORT` on `rovercan sim` (the simulator's own buses) and on `rovercan launch` (a
monitor process beside the nodes): a client of subprotocol foxglove.websocket.v1 (`websockets`,
not the project's code) gets serverInfo, an advertise of the channels and a frame it subscribed."""

from __future__ import annotations

import asyncio
import json
import signal
import subprocess
import sys
import threading
from typing import Any

import can
import pytest

from can_config import load_config

from .conftest import REPO
from .test_foxglove import ANSWER_S, LISTENS, Said, connect
from .test_mcap import ROVER
from .test_sim_cli import free_port


async def advertised(port: int, topic: str) -> tuple[dict[str, dict[str, Any]], bytes]:
    """serverInfo and advertise; then one message of ``topic`` after subscribing to it."""
    async with await connect(port) as ws:
        got: dict[str, dict[str, Any]] = {}
        while "advertise" not in got or "serverInfo" not in got:
            message = json.loads(await asyncio.wait_for(ws.recv(), ANSWER_S))
            got[message["op"]] = message
        channel = next(c for c in got["advertise"]["channels"] if c["topic"] == topic)
        await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 3, "channelId": channel["id"]}]}))
        while True:
            data = await asyncio.wait_for(ws.recv(), ANSWER_S)
            if isinstance(data, bytes) and data[0] == 1:
                return got, data


def stopped(proc: subprocess.Popen[str], *said: Said) -> str:
    """Stopped with SIGINT; what it said on the streams read by ``said`` (stderr last)."""
    proc.send_signal(signal.SIGINT)
    proc.wait(timeout=60)
    return "".join(s.close() for s in said)


@pytest.mark.slow
def test_sim_serves_the_view_of_its_buses() -> None:
    port, view = free_port(), free_port()
    sim = subprocess.Popen([sys.executable, "-m", "rovercan", "sim", "--config", str(ROVER), "--port", str(port),
                            "--foxglove", str(view)], cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    assert sim.stdout is not None and "simulated drive" in sim.stdout.readline()
    out, err_said = Said(sim.stdout), Said(sim.stderr)
    done = threading.Event()

    def traffic() -> None:  # an idle simulated drive says nothing: another node on can1 does
        with can.Bus(interface="socketcand", channel="can1", host="127.0.0.1", port=port) as bus:
            while not done.wait(0.2):
                bus.send(can.Message(arbitration_id=0x77E, data=b"\x05", is_extended_id=False))

    talker = threading.Thread(target=traffic, daemon=True)
    talker.start()
    try:
        out.wait(LISTENS, "the simulator's view to listen")
        got, data = asyncio.run(advertised(view, "/can/frames"))
    finally:
        done.set()
        talker.join(10)
        err = stopped(sim, out, err_said)
    assert sim.returncode == 0, err
    topics = {c["topic"] for c in got["advertise"]["channels"]}
    assert {"/can/frames", "/joint_states", *(f"/drives/{d.name}/status" for d in load_config(ROVER).drives)} <= topics
    assert int.from_bytes(data[1:5], "little") == 3


@pytest.mark.slow
@pytest.mark.alone  # the launched rover, its simulator and the view: beside another worker and the VM, over the 120 s test bound
def test_launch_serves_the_view_beside_the_nodes() -> None:
    view = free_port()
    launch = subprocess.Popen([sys.executable, "-m", "rovercan", "launch", "ros/rovercan_bringup/launch/motor_launch.xml",
                               "sim:=true", "--foxglove", str(view)], cwd=REPO, stdout=subprocess.PIPE,
                              stderr=subprocess.PIPE, text=True)
    out, err_said = Said(launch.stdout), Said(launch.stderr)
    try:
        err_said.wait(LISTENS, "the launch's monitor to say its view listens")  # the monitor's stderr is the launch's
        got, _ = asyncio.run(advertised(view, "/can/frames"))
    finally:
        err = stopped(launch, out, err_said)
    assert got["serverInfo"]["name"] == "rovercan", err
    assert {"/can/frames", "/joint_states"} <= {c["topic"] for c in got["advertise"]["channels"]}
