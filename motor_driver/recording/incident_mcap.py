"""An incident's frames as an MCAP file beside its BLF (ROS 2 messages, as Foxglove and
``ros2 bag`` open them): the raw frames, and with the rover's config every drive decoded
(:class:`motor_driver.recording.busview.BusView`), the incident's events as diagnostics at their times.

Owner: the flight recorder's writer thread, or the CLI's thread that calls; no state kept.
"""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

from can_config.model import RoverConfig
from motor_driver.diagnostics.health import ERROR
from motor_driver.recording.busview import FROM_DRIVER, BusView, Frame, UnitObjects, view_drives
from motor_driver.recording.mcap_out import UNITS_METADATA, McapSink, units_metadata


def write_incident_mcap(path: Path, frames: Sequence[Frame], events: Sequence[tuple[float, str, str]],
                        config: RoverConfig | None, metadata: dict[str, str],
                        units: Mapping[str, UnitObjects] | None = None) -> None:
    """``frames`` (the ring's, every bus's in arrival order) into ``path``, in time order;
    ``events``: (time, drive or bus, text), each a diagnostic of level ERROR among the frames at
    its time; with ``config``, the drives decoded in ``units`` (their unit objects as the driver
    read them at boot) where given, and their units in its metadata (:data:`UNITS_METADATA`)."""
    pending = sorted(events)
    with McapSink(path, metadata) as sink:
        drives = view_drives(config, units, FROM_DRIVER) if config is not None else []
        view = BusView(drives, sink, hold_s=0.0)  # sorted here: nothing to wait for
        in_time = getattr(frames, "in_time", None)  # the flight recorder's: in time order, unpacked as read
        for frame in in_time() if in_time is not None else sorted(frames, key=lambda f: f[0]):
            while pending and pending[0][0] <= frame[0]:
                t, who, text = pending.pop(0)
                view.incident(t, who, text, ERROR)
            view.feed(frame)
        view.finish()
        for t, who, text in pending:
            view.incident(t, who, text, ERROR)
        if config is not None:
            sink.add_metadata(UNITS_METADATA, units_metadata(view))
