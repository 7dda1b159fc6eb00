"""The live view's clients are served apart (rovercan/bench/liveview.py): a Foxglove client that
connects, subscribes and stops reading (a real websockets client whose socket is no longer read)
holds at most its queue's worth of messages in the server, and its dropped count grows, while a
second client that reads is still served, up to the last message sent. Requests the server does
not serve are answered with an error status, the connection kept."""

from __future__ import annotations

import asyncio
import json
import socket
import time
from collections.abc import Callable
from typing import Any

import pytest

from rovercan.bench.liveview import SUBPROTOCOL, ClientStats, LiveView

websockets = pytest.importorskip("websockets")

from motor_driver.recording.ros2defs import DIAGNOSTIC_ARRAY  # noqa: E402

#: Bound for hangs, not a verdict.
HANG_S = 60.0
QUEUE = 64
TOPIC = "/diagnostics"


def diagnostics(text: str) -> dict[str, Any]:
    """A DiagnosticArray of about 4 kB: the slow client's socket buffers fill after a few hundred."""
    return {"header": {"stamp": {"sec": 1, "nanosec": 0}, "frame_id": ""},
            "status": [{"level": 0, "name": "rovercan: a", "message": text + " " + "x" * 4000, "hardware_id": "",
                        "values": []}]}


async def connect(port: int, **kwargs: Any) -> Any:
    ws = await websockets.connect(f"ws://127.0.0.1:{port}", subprotocols=[SUBPROTOCOL], compression=None,
                                  ping_interval=None, **kwargs)  # no keepalive: the slow one answers no ping
    got: dict[str, Any] = {}
    while "advertise" not in got or "serverInfo" not in got:
        message = json.loads(await asyncio.wait_for(ws.recv(), HANG_S))
        got[message["op"]] = message
    channel = next(c["id"] for c in got["advertise"]["channels"] if c["topic"] == TOPIC)
    await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 5, "channelId": channel}]}))
    return ws


async def until(predicate: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + HANG_S
    while not predicate():
        assert time.monotonic() < deadline, f"no {what} within {HANG_S:g} s"
        await asyncio.sleep(0.01)


def stats(view: LiveView, name: str) -> ClientStats:
    return next(c for c in view.clients() if c.name == name)


async def slow_and_good(view: LiveView) -> None:
    stalled = socket.socket()
    stalled.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, 4096)  # a small window: it fills soon
    stalled.connect(("127.0.0.1", view.port))
    slow_name = f"127.0.0.1:{stalled.getsockname()[1]}"
    slow = await connect(view.port, sock=stalled, max_queue=1)  # reads no more: its library stops reading too
    good = await connect(view.port)
    await until(lambda: len(view.clients()) == 2 and all(c.subscriptions == 1 for c in view.clients()),
                "two subscribed clients")
    received: list[bytes] = []

    async def read() -> None:
        async for data in good:
            if isinstance(data, bytes) and data[0] == 1:
                received.append(data)

    reader = asyncio.create_task(read())
    peak, n = 0, 0

    def send(text: str) -> None:
        nonlocal peak, n
        view(TOPIC, DIAGNOSTIC_ARRAY, diagnostics(text), n)
        n += 1
        peak = max(peak, *(c.queued for c in view.clients()))

    deadline = time.monotonic() + HANG_S
    while stats(view, slow_name).dropped == 0:  # until its socket's buffers and its queue are full
        assert time.monotonic() < deadline, "the slow client never dropped a message"
        send(f"m{n}")
        await asyncio.sleep(0)
    got = len(received)
    while stats(view, slow_name).dropped < 10 * QUEUE:  # and it goes on dropping
        assert time.monotonic() < deadline, f"the slow client dropped only {stats(view, slow_name).dropped}"
        send(f"m{n}")
        await asyncio.sleep(0)
    send("last")
    await until(lambda: bool(received) and b"last " in received[-1], "last message at the reading client")
    assert len(received) > got  # served after the slow one began to drop
    assert peak <= QUEUE and stats(view, slow_name).queued <= QUEUE  # bounded, all along
    reader.cancel()
    await good.close()
    slow.transport.abort()


def test_a_slow_client_is_bounded_and_the_others_served() -> None:
    view = LiveView([(TOPIC, DIAGNOSTIC_ARRAY)], "127.0.0.1", 0, queue_size=QUEUE, ping_interval_s=None)
    try:
        asyncio.run(slow_and_good(view))
    finally:
        view.close()


async def refused(view: LiveView) -> dict[str, Any]:
    ws = await connect(view.port)
    await ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": 1, "channelId": 99}]}))
    status = json.loads(await asyncio.wait_for(ws.recv(), HANG_S))
    await ws.send(json.dumps({"op": "unsubscribe", "subscriptionIds": [5]}))
    await until(lambda: [c.subscriptions for c in view.clients()] == [0], "the unsubscribe")
    await ws.close()
    return status


def test_a_request_not_served_is_answered_and_the_client_stays() -> None:
    view = LiveView([(TOPIC, DIAGNOSTIC_ARRAY)], "127.0.0.1", 0)
    try:
        status = asyncio.run(refused(view))
    finally:
        view.close()
    assert status["op"] == "status" and status["level"] == 2 and "channel 99 is not advertised" in status["message"]
