"""Writing the bus to an MCAP file of the ROS 2 profile (ros2msg schemas, CDR messages), as
``ros2 bag`` and Foxglove read it; no rclpy (mcap-ros2-support encodes CDR from the definitions).

Written as it comes: messages go into zstd-compressed chunks of :data:`CHUNK_BYTES`, so the
memory used stays bounded whatever the length of the recording. Owner: the thread that writes.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from pathlib import Path
from types import TracebackType
from typing import IO, Any

from can_config.model import RoverConfig
from motor_driver.recording.busview import BusView, Frame, view_drives
from motor_driver.recording.ros2defs import schema_text

logger = logging.getLogger(__name__)

#: Uncompressed bytes per chunk: about a second of the rover's frames at 100 Hz.
CHUNK_BYTES = 1024 * 1024
LIBRARY = "rovercan"


class McapSink:
    """An MCAP file being written; call it with (topic, type, message, time ns) as
    :data:`motor_driver.recording.busview.Emit`. ``close()`` writes the summary; it is idempotent."""

    def __init__(self, path: str | Path, metadata: dict[str, str] | None = None) -> None:
        from mcap.writer import CompressionType
        from mcap_ros2.writer import Writer

        self.path = Path(path)
        self._file: IO[bytes] = self.path.open("wb")
        self._writer = Writer(self._file, chunk_size=CHUNK_BYTES, compression=CompressionType.ZSTD)
        self._schemas: dict[str, Any] = {}
        self.messages = 0
        if metadata:
            self._writer.add_metadata(LIBRARY, metadata)
        self._closed = False

    def __call__(self, topic: str, type_name: str, message: dict[str, Any], time_ns: int) -> None:
        schema = self._schemas.get(type_name)
        if schema is None:
            schema = self._schemas[type_name] = self._writer.register_msgdef(type_name, schema_text(type_name))
        self._writer.write_message(topic, schema, message, log_time=time_ns, publish_time=time_ns)
        self.messages += 1

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        try:
            self._writer.finish()
        finally:
            self._file.close()

    def __enter__(self) -> McapSink:
        return self

    def __exit__(self, kind: type[BaseException] | None, err: BaseException | None, tb: TracebackType | None) -> None:
        self.close()


def write_mcap(path: str | Path, frames: Iterable[Frame], config: RoverConfig | None = None,
               metadata: dict[str, str] | None = None) -> int:
    """Every frame of ``frames`` (time-ordered) into ``path``, with ``config`` its drives decoded;
    returns the number of frames."""
    n = 0
    with McapSink(path, metadata) as sink:
        view = BusView(view_drives(config) if config is not None else [], sink)
        for frame in frames:
            view.feed(frame)
            n += 1
        view.finish()
    return n
