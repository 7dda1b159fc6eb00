"""An SDO client that takes only the answers to its own request.

canopen's SdoClient takes every frame on the node's SDO answer COB-ID (0x580 + node) for the
answer to its request. Two clients of one node (the driver and a bench command beside it, or a
second tool) share that COB-ID: each then hears the answers to the other's requests, and an
abort of the other's read ("object does not exist") failed a bench read of 0x6064 beside a
booting driver. A late answer to this client's own earlier request is the same case.

CiA 301 makes an answer say what it answers: an initiate answer and every abort name the
object (index and sub-index, the multiplexer), and each request has one kind of answer. This
client drops, while it waits, an answer of another kind or about another object (logged), and
waits on for its own within the same timeout. What it cannot tell apart (a segment of another
transfer of the same kind) is left to canopen's toggle check and SdoPort's one retry.

Owner: the calling thread, one transfer at a time (the drive's SDO port serialises callers);
the bus's receive thread only hands it the answers to its own request.
"""

from __future__ import annotations

import logging
import queue
import struct

import canopen
from canopen.objectdictionary import ObjectDictionary
from canopen.sdo.client import SdoClient

from motor_driver.bus.adapters import receive_behind
from motor_driver.process.held import POLL_S, HeldDeadline, ReadBehind

logger = logging.getLogger(__name__)

_ABORT = 0x80
#: the command class of a request (its top three bits) -> the class of its answer
_ANSWER_CLASS = {0x40: 0x40,  # upload initiate -> upload initiate answer (names the object)
                 0x20: 0x60,  # download initiate -> download initiate answer (names the object)
                 0x60: 0x00,  # upload segment -> upload segment
                 0x00: 0x20}  # download segment -> download segment answer
_NAMES_OBJECT = (0x40, 0x60)


class ReceiveBehindError(canopen.SdoCommunicationError):  # type: ignore[misc]
    """No answer read, and this driver's receive thread was still behind the bus at the bound
    (motor_driver.process.held.ReadBehind): the drive may have answered; the host was late."""


class MultiplexedSdoClient(SdoClient):  # type: ignore[misc]
    """canopen's SDO client, keeping only answers of the kind and object of its own request."""

    def __init__(self, rx_cobid: int, tx_cobid: int, od: ObjectDictionary) -> None:
        super().__init__(rx_cobid, tx_cobid, od)
        self._answer_class: int | None = None  # None: no filter (block transfers, an abort sent)
        self._object = b""  # the transfer's multiplexer: index (LE) and sub-index

    def send_request(self, request: bytes | bytearray) -> None:
        kind = request[0] & 0xE0
        if kind in (0x40, 0x20):
            self._object = bytes(request[1:4])
        self._answer_class = _ANSWER_CLASS.get(kind)
        super().send_request(request)

    def read_response(self) -> bytes:
        """The answer to this client's request, or canopen's errors (an abort of this transfer,
        no answer within RESPONSE_TIMEOUT); answers to other requests are dropped."""
        deadline = HeldDeadline(self.RESPONSE_TIMEOUT)  # a hold of this process is not the drive's silence
        behind = ReadBehind(lambda: receive_behind(getattr(self.network, "bus", None)))  # nor a starved reader
        while True:
            left = deadline.remaining()
            judged = left <= 0 and not behind.wait_on()  # past the deadline, the receive thread not behind
            try:
                if judged:  # what the receive thread handed on as it caught up, else no answer
                    response: bytes = self.responses.get_nowait()
                else:
                    response = self.responses.get(block=True, timeout=min(left, POLL_S) if left > 0 else POLL_S)
            except queue.Empty:
                if not judged:
                    continue
                error = ReceiveBehindError if behind.gave_up else canopen.SdoCommunicationError
                raise error("No SDO response received" + deadline.said() + behind.said()) from None
            why = self._not_ours(response)
            if why is None:
                break
            logger.info("node %d: SDO answer %s dropped: %s", self.rx_cobid - 0x600, response.hex(" "), why)
        if response[0] == _ABORT:
            (code,) = struct.unpack_from("<L", response.ljust(8, b"\0"), 4)
            raise canopen.SdoAbortedError(code)
        return response

    def _not_ours(self, response: bytes) -> str | None:
        """Why ``response`` is not the answer to the request in flight, or None when it may be."""
        if self._answer_class is None or not response:
            return None
        kind = response[0] & 0xE0
        names = bytes(response[1:4])
        if response[0] == _ABORT:
            return None if names == self._object else f"an abort of {_name(names)}, not of {_name(self._object)}"
        if kind != self._answer_class:
            return f"an answer of class 0x{kind:02X}, not the 0x{self._answer_class:02X} this request has"
        if kind in _NAMES_OBJECT and names != self._object:
            return f"it answers {_name(names)}, not {_name(self._object)}"
        return None


def _name(multiplexer: bytes) -> str:
    if len(multiplexer) < 3:
        return "no object"
    return f"0x{int.from_bytes(multiplexer[:2], 'little'):04X}:{multiplexer[2]}"


class OwnAnswersNode(canopen.RemoteNode):  # type: ignore[misc]
    """canopen's RemoteNode whose SDO channels are MultiplexedSdoClients."""

    def add_sdo(self, rx_cobid: int, tx_cobid: int) -> MultiplexedSdoClient:
        client = MultiplexedSdoClient(rx_cobid, tx_cobid, self.object_dictionary)
        self.sdo_channels.append(client)
        if self.has_network():
            self.network.subscribe(client.tx_cobid, client.on_response)
        return client
