"""An in-process python-can bus on a :class:`~virtual_can.engine.BusEngine` channel.

Registered as the python-can interface ``rovercan`` (entry point), so code that opens a
bus from configuration can take it too: ``can.Bus(interface="rovercan", channel="can0",
engine=engine)``. Unlike python-can's ``virtual`` interface it shares the engine's wire
time, fault injection and statistics with the socketcand server.

Owner: the caller's thread sends and receives; the engine's thread delivers into the bus's queue.
"""

from __future__ import annotations

import queue
from typing import Any

import can

from can_config.errors import SimError
from virtual_can.engine import BusEngine

#: Frames a reader may fall behind before the oldest are dropped (as a controller's FIFO).
RX_QUEUE_FRAMES = 100_000


class VirtualBus(can.BusABC):
    """A python-can bus attached to one channel of a :class:`BusEngine`."""

    def __init__(self, channel: Any = "can0", *, engine: BusEngine | None = None,
                 receive_own_messages: bool = False, **kwargs: Any) -> None:
        if engine is None:
            raise SimError("VirtualBus needs engine=BusEngine(); the in-process bus lives in one"
                           " engine object shared by everything on it")
        self._queue: queue.SimpleQueue[can.Message] = queue.SimpleQueue()
        self._receive_own = receive_own_messages
        self.channel_info = f"rovercan virtual bus {channel}"
        self._channel = engine.channel(str(channel))
        self._endpoint = self._channel.attach(self._on_frame, name=f"bus:{channel}")
        self._closed = False
        super().__init__(channel=channel, **kwargs)

    def _on_frame(self, msg: can.Message) -> None:
        if self._queue.qsize() >= RX_QUEUE_FRAMES:
            return  # a reader that does not keep up loses the newest frames
        self._queue.put(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        try:
            msg = self._queue.get(timeout=timeout) if timeout != 0 else self._queue.get_nowait()
        except queue.Empty:
            return None, False
        return msg, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self._closed:
            raise can.CanOperationError("the virtual bus is shut down")
        # a copy: receivers must not see later changes the sender makes to its message
        out = can.Message(timestamp=0.0, arbitration_id=msg.arbitration_id, is_extended_id=msg.is_extended_id,
                          is_remote_frame=msg.is_remote_frame, dlc=msg.dlc, data=msg.data, check=False)
        self._channel.send(out, self._endpoint)
        if self._receive_own:
            self._on_frame(out)

    def shutdown(self) -> None:
        if self._closed:
            return
        self._closed = True
        self._endpoint.detach()
        super().shutdown()
