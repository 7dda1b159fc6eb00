"""Writing the bus to an MCAP file of the ROS 2 profile (ros2msg schemas, CDR messages), as
``ros2 bag`` and Foxglove read it; no rclpy (mcap-ros2-support encodes CDR from the definitions).

Written as it comes: messages go into zstd-compressed chunks of :data:`CHUNK_BYTES`, so the
memory used stays bounded whatever the length of the recording. Owner: the thread that writes.

With a config, the file ends with the metadata record :data:`UNITS_METADATA`: each drive's units
as the view decoded it (JSON: where from, the unit objects, the scale), and under
:data:`CONFIG_ONLY_KEY` the drives decoded in the config's units alone ("" none), which the
writer also says in a warning (:func:`config_units_warning`). ``rovercan decode`` of such a file
decodes with the units it holds.
"""

from __future__ import annotations

import json
import logging
from collections.abc import Iterable, Mapping
from pathlib import Path
from types import TracebackType
from typing import IO, Any

from can_config.model import RoverConfig
from motor_driver.recording.busview import BusView, Frame, UnitObjects, key_of, view_drives
from motor_driver.recording.ros2defs import schema_text
from motor_driver.recording.timemerge import FILE_HOLD_S

logger = logging.getLogger(__name__)

#: Uncompressed bytes per chunk: about a second of the rover's frames at 100 Hz.
CHUNK_BYTES = 1024 * 1024
LIBRARY = "rovercan"
#: The metadata record of the drives' units, and its key naming those decoded in the config's units alone.
UNITS_METADATA = "rovercan.units"
CONFIG_ONLY_KEY = "drives_in_config_units"


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

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        """A metadata record (written where it comes; readers find it through the summary)."""
        self._writer.add_metadata(name, data)

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


def units_metadata(view: BusView) -> dict[str, str]:
    """The :data:`UNITS_METADATA` record of ``view``'s drives."""
    units = {name: json.dumps(u, sort_keys=True) for name, u in view.units().items()}
    return {CONFIG_ONLY_KEY: ", ".join(view.config_units()), **units}


def recorded_units(metadata: Mapping[str, str]) -> dict[str, dict[tuple[int, int], int]]:
    """The drives' unit objects from a :data:`UNITS_METADATA` record (only those the drive gave)."""
    units: dict[str, dict[tuple[int, int], int]] = {}
    for name, text in metadata.items():
        if name == CONFIG_ONLY_KEY:
            continue
        entry = json.loads(text)
        if entry.get("from") != "config" and entry.get("objects"):
            units[name] = {key_of(k): int(v) for k, v in entry["objects"].items()}
    return units


def config_units_warning(command: str, drives: list[str]) -> str:
    """What a recording decoded in the config's units says, naming the drives."""
    return (f"{command}: warning: {', '.join(drives)} decoded in the config's units: no answer of the drive to the"
            " driver's reads of its unit objects (0x608F, 0x6091, 0x6092, 0x60A8-0x60AA, 0x6076) is in the frames (the"
            " recording began after the driver booted it), nor in the recording's metadata; metadata"
            f" {UNITS_METADATA}.{CONFIG_ONLY_KEY} names them. Record from before the driver starts to have the drive's own.")


def write_mcap(path: str | Path, frames: Iterable[Frame], config: RoverConfig | None = None,
               metadata: dict[str, str] | None = None, units: Mapping[str, UnitObjects] | None = None
               ) -> tuple[int, list[str]]:
    """Every frame of ``frames`` (any bus, as read) into ``path``, with ``config`` its drives
    decoded (``units``: their unit objects where a recording's metadata gave them); returns the
    number of frames and the drives decoded in the config's units alone."""
    n = 0
    with McapSink(path, metadata) as sink:
        view = BusView(view_drives(config, units) if config is not None else [], sink, hold_s=FILE_HOLD_S)
        for frame in frames:
            view.feed(frame)
            n += 1
        view.finish()
        if config is not None:
            sink.add_metadata(UNITS_METADATA, units_metadata(view))
    return n, view.config_units() if config is not None else []
