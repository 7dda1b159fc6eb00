"""The flight recorder's incident files, as a passive format shared by the driver (which
writes them, :mod:`motor_driver.recorder`) and the simulator (which replays them,
``rovercan sim --scenario-from-log``).

An incident is ``<stem>.json`` (this summary) beside ``<stem>.blf`` (every frame of every bus,
BLF channel ``n`` being the bus ``channels[str(n)]``) and, with matplotlib, ``<stem>.png``.
"""

from __future__ import annotations

import itertools
import json
import statistics
from pathlib import Path
from typing import Any

import can

from can_config.errors import ConfigError
from can_config.textfile import read_text_file

FORMAT = "rovercan-incident-1"
#: A drive's heartbeat gap longer than this many of its periods (and SILENCE_MIN_S) is a silence.
SILENCE_PERIODS = 3.0
SILENCE_MIN_S = 0.1
#: A power cycle replayed is at least this long (the drive's boot-up came after a silence).
POWER_OFF_MIN_S = 0.05


def load_incident(path: Path | str) -> dict[str, Any]:
    """An incident's summary from its .json (or the .blf / .png beside it)."""
    json_path = Path(path).with_suffix(".json")
    try:
        summary = json.loads(read_text_file(json_path, "incident summary", "give the .json of an incident"))
    except json.JSONDecodeError as err:
        raise ConfigError(f"{json_path}: not an incident summary (invalid JSON: {err})") from err
    if not isinstance(summary, dict) or summary.get("format") != FORMAT:
        raise ConfigError(f"{json_path}: not a rovercan incident summary (format {FORMAT!r} expected);"
                          " give a .json the flight recorder wrote")
    return summary


def incident_frames(path: Path | str, summary: dict[str, Any]) -> list[tuple[str, can.Message]]:
    """(bus name, frame) of the incident's BLF, in time order."""
    blf = Path(path).with_name(str(summary.get("blf") or Path(path).with_suffix(".blf").name))
    channels: dict[str, str] = summary.get("channels", {})
    try:
        with can.BLFReader(blf) as reader:
            return [(channels.get(str(msg.channel), str(msg.channel)), msg) for msg in reader]
    except (OSError, ValueError, can.CanError) as err:
        raise ConfigError(f"{blf}: cannot read the incident's frames ({err})") from err


def fault_steps(path: Path | str, delay_s: float = 2.0) -> list[dict[str, Any]]:
    """The drives' side of an incident as simulator scenario steps: their EMCYs (``fault``),
    power cycles (a silence ended by a boot-up) and silences (``unplug`` / ``plug``), at their
    times, the first of them ``delay_s`` after the scenario starts."""
    summary = load_incident(path)
    frames = incident_frames(path, summary)
    bus_channel: dict[str, str] = summary.get("bus_channels", {})
    drives = {(d["bus"], int(d["node_id"])) for d in summary.get("drives", [])}
    nodes = {(bus_channel.get(bus, bus), node) for bus, node in drives}
    steps: list[tuple[float, dict[str, Any]]] = []
    beats: dict[tuple[str, int], list[tuple[float, bool]]] = {}
    for bus, msg in frames:
        channel = bus_channel.get(bus, bus)
        cob = msg.arbitration_id
        if msg.is_extended_id or msg.is_error_frame:
            continue
        if 0x081 <= cob <= 0x0FF and (channel, cob - 0x80) in nodes and len(msg.data) >= 2:
            code = int.from_bytes(msg.data[:2], "little")
            if code:
                steps.append((msg.timestamp, {"node": cob - 0x80, "channel": channel, "action": "fault", "code": code}))
        elif 0x701 <= cob <= 0x77F and (channel, cob - 0x700) in nodes and msg.data:
            beats.setdefault((channel, cob - 0x700), []).append((msg.timestamp, msg.data[0] == 0))
    for (channel, node), seen in beats.items():
        gaps = [b[0] - a[0] for a, b in itertools.pairwise(seen) if not b[1]]
        period = statistics.median(gaps) if gaps else 0.1
        for (t_prev, _), (t, bootup) in itertools.pairwise(seen):
            gap = t - t_prev
            if bootup:
                off = max(POWER_OFF_MIN_S, gap - period)
                steps.append((t - off, {"node": node, "channel": channel, "action": "power_cycle",
                                        "off_s": round(off, 3)}))
            elif gap > max(SILENCE_PERIODS * period, SILENCE_MIN_S):
                steps.append((t_prev + period, {"node": node, "channel": channel, "action": "unplug"}))
                steps.append((t, {"node": node, "channel": channel, "action": "plug"}))
    if not steps:
        return []
    t0 = min(t for t, _ in steps)
    return [{"at_s": round(delay_s + t - t0, 3), **step} for t, step in sorted(steps, key=lambda s: s[0])]
