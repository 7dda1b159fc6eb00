"""An incident's frames as an MCAP file beside its BLF (ROS 2 messages, as Foxglove and
``ros2 bag`` open them): the raw frames, and with the rover's config every drive decoded
(:class:`motor_driver.recording.busview.BusView`), the incident's events as diagnostics at their times."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

from can_config.model import RoverConfig
from motor_driver.recording.busview import ERROR, BusView, Frame, view_drives
from motor_driver.recording.mcap_out import McapSink


def write_incident_mcap(path: Path, frames: Sequence[Frame], events: Sequence[tuple[float, str, str]],
                        config: RoverConfig | None, metadata: dict[str, str]) -> None:
    """``frames`` (time-ordered) into ``path``; ``events``: (time, drive or bus, text), each a
    diagnostic of level ERROR among the frames at its time."""
    pending = sorted(events)
    with McapSink(path, metadata) as sink:
        view = BusView(view_drives(config) if config is not None else [], sink)
        for frame in frames:
            while pending and pending[0][0] <= frame[0]:
                t, who, text = pending.pop(0)
                view.incident(t, who, text, ERROR)
            view.feed(frame)
        view.finish()
        for t, who, text in pending:
            view.incident(t, who, text, ERROR)
