"""The live view's server: the Foxglove WebSocket protocol (subprotocol ``foxglove.websocket.v1``,
which Foxglove, Lichtblick and ros-foxglove-bridge's clients speak) on the websockets library,
messages as ROS 2 CDR (:mod:`motor_driver.recording.cdr`).

A client gets ``serverInfo`` and the ``advertise`` of every channel when it connects; it
subscribes to the channels it shows, and a message is encoded only while some client subscribes
to its channel. Each client has a queue of at most :data:`CLIENT_QUEUE` messages: a client that
reads slower than the bus talks loses its oldest messages, counted (:meth:`LiveView.clients`),
logged at a bounded rate and said to it in a ``status`` message; it never grows the process, and
the other clients are served as before.

Threads: the server runs on an asyncio loop of its own thread (``rovercan-foxglove``), which owns
the clients, their subscriptions and the routing table (replaced in one assignment, read by the
caller). The caller's thread (the one reading the buses) encodes and puts messages into the
clients' queues (each with its own lock; :class:`ClientQueue`) and wakes a client's writer only
when it waits: nothing it does grows the loop's work.
"""

from __future__ import annotations

import asyncio
import json
import logging
import struct
import threading
import time
from collections import deque
from dataclasses import dataclass, field
from typing import Any

from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed

from can_config.errors import ConfigError
from motor_driver.process.ratelimit import RateLimitedLog
from motor_driver.recording.cdr import encode
from motor_driver.recording.ros2defs import schema_text

logger = logging.getLogger(__name__)

SUBPROTOCOL = "foxglove.websocket.v1"
#: Messages a client may have waiting; beyond, its oldest are dropped (about 0.1 s of the rover's
#: frames at six drives' 1 kHz of traffic, or several seconds of its drives' states).
CLIENT_QUEUE = 1024
#: The server starts, or stops, within this long (a bound for a hang).
START_S = 10.0
#: A client that does not answer the closing handshake within this long is cut off.
CLOSE_S = 1.0
#: Largest message a client may send (subscribe and unsubscribe requests are small).
CLIENT_MESSAGE_MAX = 1 << 20
_MESSAGE_DATA = struct.Struct("<BIQ")  # opcode 1, subscription id, time ns; then the CDR
_STATUS_WARNING = 1
_STATUS_ERROR = 2

Item = tuple[int, int, int, bytes]  # channel id, subscription id, time ns, CDR


class ClientQueue:
    """One client's waiting messages: at most ``size``, the oldest dropped and counted. The
    caller's thread puts, the loop's thread takes, each under the queue's lock."""

    def __init__(self, size: int = CLIENT_QUEUE) -> None:
        self._items: deque[Item] = deque(maxlen=size)
        self._lock = threading.Lock()
        self._waiting = False
        self.size = size
        self.dropped = 0

    def put(self, item: Item) -> bool:
        """Queue ``item`` (the oldest dropped when full); True when the taker waits and must be woken."""
        with self._lock:
            if len(self._items) == self.size:
                self.dropped += 1
            self._items.append(item)
            woken, self._waiting = self._waiting, False
            return woken

    def take(self) -> Item | None:
        """The oldest item; None when empty (then the next :meth:`put` says to wake the taker)."""
        with self._lock:
            if self._items:
                return self._items.popleft()
            self._waiting = True
            return None

    def __len__(self) -> int:
        return len(self._items)


@dataclass
class _Client:
    """A connected client (the loop's thread): its subscriptions, its queue and its writer's wake-up."""
    name: str
    queue: ClientQueue
    wake: asyncio.Event
    subscriptions: dict[int, int] = field(default_factory=dict)  # subscription id -> channel id
    said_dropped: int = 0


@dataclass(frozen=True)
class ClientStats:
    """What :meth:`LiveView.clients` says of a connected client."""
    name: str  #: its address, host:port
    subscriptions: int
    queued: int  #: messages waiting for it now (at most ``queue_size``)
    dropped: int  #: its oldest messages dropped because it read too slowly, since it connected
    queue_size: int


class LiveView:
    """The server of ``channels`` ((topic, ROS 2 type) pairs) on ``host``:``port`` (0: any free
    one; :attr:`port` says which) until :meth:`close`. Call it as a
    :data:`motor_driver.recording.busview.Emit`: ``view(topic, type, message, time_ns)``."""

    def __init__(self, channels: list[tuple[str, str]], host: str, port: int, *, queue_size: int = CLIENT_QUEUE,
                 ping_interval_s: float | None = 20.0) -> None:
        self._ids = {topic: i for i, (topic, _) in enumerate(channels, start=1)}
        self._advertise = json.dumps({"op": "advertise", "channels": [
            {"id": self._ids[topic], "topic": topic, "encoding": "cdr", "schemaName": type_name,
             "schema": schema_text(type_name), "schemaEncoding": "ros2msg"} for topic, type_name in channels]})
        self._info = json.dumps({"op": "serverInfo", "name": "rovercan", "capabilities": [],
                                 "supportedEncodings": ["cdr"], "metadata": {}, "sessionId": str(time.time_ns())})
        self._queue_size = queue_size
        self._clients: tuple[_Client, ...] = ()  # the loop's thread replaces it
        self._routes: dict[int, tuple[tuple[_Client, int], ...]] = {}  # channel -> (client, subscription id)
        self._said = RateLimitedLog(logger)
        self._loop = asyncio.new_event_loop()
        self._thread = threading.Thread(target=self._loop.run_forever, daemon=True, name="rovercan-foxglove")
        self._thread.start()
        self._closed = False

        async def start() -> Server:
            return await serve(self._serve_client, host, port, subprotocols=[SUBPROTOCOL],  # type: ignore[list-item]
                               compression=None, max_size=CLIENT_MESSAGE_MAX, ping_interval=ping_interval_s,
                               close_timeout=CLOSE_S, logger=logger)

        try:
            self._server = asyncio.run_coroutine_threadsafe(start(), self._loop).result(START_S)
        except OSError as err:
            self._stop_loop()
            raise ConfigError(f"--foxglove {port}: cannot serve on {host}:{port} ({err}); pick a free port") from err
        except BaseException:
            self._stop_loop()
            raise
        self.port = int(next(iter(self._server.sockets)).getsockname()[1])

    # ------------------------------------------------------------------ the caller's thread
    def __call__(self, topic: str, type_name: str, message: dict[str, Any], time_ns: int) -> None:
        routes = self._routes.get(self._ids[topic])
        if not routes:
            return  # nobody shows it: not even encoded
        data = encode(type_name, message)
        for client, subscription in routes:
            if client.queue.put((self._ids[topic], subscription, time_ns, data)):
                self._loop.call_soon_threadsafe(client.wake.set)

    def clients(self) -> list[ClientStats]:
        """Every connected client's subscriptions, queue and drops, now."""
        return [ClientStats(c.name, len(c.subscriptions), len(c.queue), c.queue.dropped, c.queue.size)
                for c in self._clients]

    def close(self) -> None:
        """Every client disconnected, the server and its thread stopped. Idempotent."""
        if self._closed:
            return
        self._closed = True

        async def stop() -> None:
            self._server.close()
            await self._server.wait_closed()

        try:
            asyncio.run_coroutine_threadsafe(stop(), self._loop).result(timeout=START_S)
        finally:
            self._stop_loop()

    def _stop_loop(self) -> None:
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=START_S)
        if not self._thread.is_alive():
            self._loop.close()

    # ------------------------------------------------------------------ the loop's thread
    async def _serve_client(self, ws: ServerConnection) -> None:
        host, port = ws.remote_address[:2]
        if ws.subprotocol != SUBPROTOCOL:
            await ws.close(1002, f"speak subprotocol {SUBPROTOCOL}")
            return
        client = _Client(f"{host}:{port}", ClientQueue(self._queue_size), asyncio.Event())
        logger.info("Foxglove client %s connected", client.name)
        writer = None
        try:
            await ws.send(self._info)
            await ws.send(self._advertise)
            self._clients += (client,)
            writer = asyncio.create_task(self._write(ws, client), name=f"rovercan-foxglove {client.name}")
            async for raw in ws:
                await self._on_request(ws, client, raw)
        except ConnectionClosed:
            pass
        finally:
            self._clients = tuple(c for c in self._clients if c is not client)
            client.subscriptions.clear()
            self._route()
            if writer is not None:
                writer.cancel()
                await asyncio.gather(writer, return_exceptions=True)
            logger.info("Foxglove client %s left (%d message(s) dropped for it)", client.name, client.queue.dropped)

    async def _on_request(self, ws: ServerConnection, client: _Client, raw: str | bytes) -> None:
        """A client's subscribe or unsubscribe; anything else is answered with an error status."""
        try:
            request = json.loads(raw)
            if request["op"] == "subscribe":
                for sub in request["subscriptions"]:
                    if int(sub["channelId"]) not in self._ids.values():
                        raise ValueError(f"channel {sub['channelId']} is not advertised")
                    client.subscriptions[int(sub["id"])] = int(sub["channelId"])
            elif request["op"] == "unsubscribe":
                for sub_id in request["subscriptionIds"]:
                    client.subscriptions.pop(int(sub_id), None)
            else:
                raise ValueError(f"op {request['op']!r} is not served (subscribe, unsubscribe)")
        except (ValueError, KeyError, TypeError) as err:
            logger.warning("Foxglove client %s: request refused: %s", client.name, err)
            await ws.send(json.dumps({"op": "status", "level": _STATUS_ERROR, "message": f"refused: {err}"}))
            return
        self._route()

    def _route(self) -> None:
        """The routing table from every client's subscriptions, replaced in one assignment."""
        routes: dict[int, list[tuple[_Client, int]]] = {}
        for client in self._clients:
            for subscription, channel in client.subscriptions.items():
                routes.setdefault(channel, []).append((client, subscription))
        self._routes = {channel: tuple(pairs) for channel, pairs in routes.items()}

    async def _write(self, ws: ServerConnection, client: _Client) -> None:
        """The client's messages, oldest first, as fast as it reads them; its drops said. An
        unexpected error is logged and ends the client's connection (it may connect again)."""
        try:
            while True:
                item = client.queue.take()
                if item is None:
                    await client.wake.wait()
                    client.wake.clear()
                    continue
                channel, subscription, time_ns, data = item
                if client.subscriptions.get(subscription) != channel:
                    continue  # unsubscribed since
                await ws.send(_MESSAGE_DATA.pack(1, subscription, time_ns) + data)
                if client.queue.dropped != client.said_dropped:
                    await self._say_dropped(ws, client)
        except ConnectionClosed:
            pass
        except Exception as err:  # supervised: said, and the client's connection ends
            logger.error("Foxglove client %s: its writer failed: %r; disconnecting it", client.name, err)
            await ws.close(1011, "server error")

    async def _say_dropped(self, ws: ServerConnection, client: _Client) -> None:
        """The client's drops, at a bounded rate, in the log and to the client."""
        dropped = client.queue.dropped
        if self._said.log(logging.WARNING, client.name, "Foxglove client %s reads too slowly: %d message(s)"
                          " dropped, oldest first (it keeps the newest %d)", client.name, dropped, client.queue.size):
            client.said_dropped = dropped
            await ws.send(json.dumps({"op": "status", "level": _STATUS_WARNING, "id": "rovercan-dropped",
                                      "message": f"rovercan: this client reads too slowly: {dropped} message(s)"
                                                 f" dropped, oldest first"}))


__all__ = ["CLIENT_QUEUE", "SUBPROTOCOL", "ClientQueue", "ClientStats", "LiveView"]
