"""SDO server of the simulated drive (CiA 301 7.2.4), written from the standard.

Expedited and segmented upload and download; block transfer is answered with an abort
(command specifier not supported), as many drives do. :meth:`SdoServer.handle` maps one
request payload to one response payload, so it is tested byte for byte.

Owner: the simulator's runner thread, all of it.
"""

from __future__ import annotations

import struct
from typing import TypeVar

from virtual_can.sim.objects import ABORT_GENERAL, ObjectStore, SdoAbort

ABORT_TOGGLE = 0x0503_0000
ABORT_COMMAND = 0x0504_0001

_Buffer = TypeVar("_Buffer", bytes, bytearray)


def abort_frame(index: int, subindex: int, code: int) -> bytes:
    return struct.pack("<BHBI", 0x80, index, subindex, code)


class SdoServer:
    def __init__(self, store: ObjectStore) -> None:
        self.store = store
        self._upload: bytes | None = None
        self._download: bytearray | None = None
        self._mux = (0, 0)
        self._toggle = 0
        #: fault injection: abort every request with this code (None: answer normally)
        self.force_abort: int | None = None

    def handle(self, req: bytes) -> bytes | None:
        if len(req) != 8:
            return None  # not an SDO request frame; a real server ignores it
        ccs = req[0] >> 5
        index, subindex = struct.unpack_from("<HB", req, 1)
        if ccs == 4:  # abort from the client
            self._upload = self._download = None
            return None
        if self.force_abort is not None and ccs in (1, 2):
            return abort_frame(index, subindex, self.force_abort)
        try:
            if ccs == 2:
                return self._initiate_upload(index, subindex)
            if ccs == 3:
                return self._upload_segment(req)
            if ccs == 1:
                return self._initiate_download(req, index, subindex)
            if ccs == 0:
                return self._download_segment(req)
        except SdoAbort as err:
            self._upload = self._download = None
            return abort_frame(err.index, err.subindex, err.code)
        except Exception:  # never let a request crash the drive
            self._upload = self._download = None
            return abort_frame(index, subindex, ABORT_GENERAL)
        index, subindex = self._mux
        return abort_frame(index, subindex, ABORT_COMMAND)

    def _initiate_upload(self, index: int, subindex: int) -> bytes:
        data = self.store.read(index, subindex)
        if len(data) <= 4:
            n = 4 - len(data)
            return struct.pack("<BHB", 0x43 | (n << 2), index, subindex) + data + bytes(n)
        self._upload = data
        self._mux = (index, subindex)
        self._toggle = 0
        return struct.pack("<BHBI", 0x41, index, subindex, len(data))

    def _segment(self, req: bytes, pending: _Buffer | None, what: str) -> tuple[_Buffer, int]:
        """The transfer a segment request continues, and its toggle bit: aborts a segment of no
        transfer, or one whose toggle does not alternate."""
        if pending is None:
            raise SdoAbort(ABORT_COMMAND, *self._mux, f"no {what} in progress")
        toggle = (req[0] >> 4) & 1
        if toggle != self._toggle:
            raise SdoAbort(ABORT_TOGGLE, *self._mux, "toggle bit")
        return pending, toggle

    def _upload_segment(self, req: bytes) -> bytes:
        upload, toggle = self._segment(req, self._upload, "upload")
        chunk, self._upload = upload[:7], upload[7:]
        last = not self._upload
        n = 7 - len(chunk)
        head = (toggle << 4) | (n << 1) | int(last)
        self._toggle ^= 1
        if last:
            self._upload = None
        return bytes([head]) + chunk + bytes(n)

    def _initiate_download(self, req: bytes, index: int, subindex: int) -> bytes:
        expedited = req[0] & 0x02
        size_given = req[0] & 0x01
        if expedited:
            n = (req[0] >> 2) & 0x03 if size_given else 0
            self.store.write(index, subindex, bytes(req[4:8 - n]))
        else:
            self._download = bytearray()
            self._mux = (index, subindex)
            self._toggle = 0
        return struct.pack("<BHBI", 0x60, index, subindex, 0)

    def _download_segment(self, req: bytes) -> bytes:
        download, toggle = self._segment(req, self._download, "download")
        n = (req[0] >> 1) & 0x07
        download += req[1:8 - n]
        self._toggle ^= 1
        if req[0] & 0x01:
            data, self._download = bytes(download), None
            self.store.write(*self._mux, data)
        return bytes([0x20 | (toggle << 4)]) + bytes(7)
