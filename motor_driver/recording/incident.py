"""The flight recorder's incident files read back: the driver writes them
(:mod:`motor_driver.recording.flight`), the CLI prints them (``rovercan incident``) and turns them into a
simulator scenario (``rovercan sim --scenario-from-log``; the simulator itself never reads one).

An incident is ``<stem>.json`` (this summary) beside ``<stem>.blf`` (every frame of every bus,
BLF channel ``n`` being the bus ``channels[str(n)]``) and, with matplotlib, ``<stem>.png``.

Owner: the calling thread; no state kept between calls.
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
from motor_driver.recording.files import RECORDING_ERRORS, blf_problem, frame_problem

FORMAT = "rovercan-incident-1"
#: A drive's heartbeat gap longer than this many of its periods (and SILENCE_MIN_S) is a silence.
SILENCE_PERIODS = 3.0
SILENCE_MIN_S = 0.1
#: A power cycle replayed is at least this long (the drive's boot-up came after a silence).
POWER_OFF_MIN_S = 0.05
#: A summary holds its events and a few seconds of drive states: tens of kB to a few MB.
SUMMARY_MAX_BYTES = 64 << 20


def load_incident(path: Path | str) -> dict[str, Any]:
    """An incident's summary from its .json (or the .blf / .png beside it)."""
    json_path = Path(path).with_suffix(".json")
    try:
        summary = json.loads(read_text_file(json_path, "incident summary", "give the .json of an incident",
                                            max_bytes=SUMMARY_MAX_BYTES))
    except json.JSONDecodeError as err:
        raise ConfigError(f"{json_path}: not an incident summary (invalid JSON: {err.msg}, line {err.lineno})") from err
    except ConfigError:  # the file's own reading said why (missing, a folder, binary): a ValueError too
        raise
    except (RecursionError, ValueError) as err:  # nesting past the parser's depth; a 5,000-digit number
        raise ConfigError(f"{json_path}: not an incident summary (it nests deeper, or holds longer numbers, than"
                          " any summary the flight recorder writes); give a .json the flight recorder wrote") from err
    if not isinstance(summary, dict) or summary.get("format") != FORMAT:
        raise ConfigError(f"{json_path}: not a rovercan incident summary (format {FORMAT!r} expected);"
                          " give a .json the flight recorder wrote")
    problem = _summary_problem(summary)
    if problem:
        raise ConfigError(f"{json_path}: a damaged incident summary ({FORMAT}): {problem}; give a .json the flight"
                          " recorder wrote, unedited")
    return summary


_NUMBER = (int, float)
_OPTIONAL_STR = (str, type(None))
#: Each field of a summary and the types it may hold (bool is refused where a number is asked).
_FIELDS: dict[str, tuple[type, ...]] = {
    "kind": (str,), "time": (str,), "t": _NUMBER, "events": (list,), "window_s": (list,), "frames": (int,),
    "channels": (dict,), "bus_channels": (dict,), "drives": (list,), "config": _OPTIONAL_STR, "blf": _OPTIONAL_STR,
    "png": _OPTIONAL_STR, "states": (dict,),
}
_EVENT_FIELDS: dict[str, tuple[type, ...]] = {
    "kind": (str,), "t": _NUMBER, "bus": (str,), "node": (int, type(None)), "drive": _OPTIONAL_STR,
    "code": (int, type(None)), "text": (str,),
}
_DRIVE_FIELDS: dict[str, tuple[type, ...]] = {"name": (str,), "bus": (str,), "node_id": (int,)}


def _wrong(value: Any, types: tuple[type, ...]) -> bool:
    return isinstance(value, bool) or not isinstance(value, types)


def _record_problem(record: Any, fields: dict[str, tuple[type, ...]], where: str) -> str | None:
    if not isinstance(record, dict):
        return f"{where} is {type(record).__name__}, not an object"
    for key, types in fields.items():
        if key not in record:
            return f"{where} has no {key!r}"
        if _wrong(record[key], types):
            wanted = " or ".join("null" if t is type(None) else t.__name__ for t in types)
            return f"{where}.{key} is {record[key]!r}, not {wanted}"
    return None


def _summary_problem(summary: dict[str, Any]) -> str | None:
    """What is wrong with a summary's fields (None: it is whole), as read by ``incident``."""
    problem = _record_problem(summary, _FIELDS, "the summary")
    if problem:
        return problem
    if not summary["events"]:
        return "it lists no events"
    window = summary["window_s"]
    if len(window) != 2 or any(_wrong(t, _NUMBER) for t in window):
        return f"window_s is {window!r}, not [start, end] in s"
    for i, event in enumerate(summary["events"]):
        if problem := _record_problem(event, _EVENT_FIELDS, f"events[{i}]"):
            return problem
    for i, drive in enumerate(summary["drives"]):
        if problem := _record_problem(drive, _DRIVE_FIELDS, f"drives[{i}]"):
            return problem
    blf = summary["blf"]
    if blf is not None and (not blf or Path(blf).name != blf):
        return f"blf is {blf!r}, not the name of a file beside the summary"
    for name in ("channels", "bus_channels"):
        if any(not isinstance(v, str) for v in summary[name].values()):
            return f"{name} maps to something other than bus names"
    return None


def incident_frames(path: Path | str, summary: dict[str, Any]) -> list[tuple[str, can.Message]]:
    """(bus name, frame) of the incident's BLF, in time order."""
    blf = Path(path).with_name(str(summary.get("blf") or Path(path).with_suffix(".blf").name))
    channels: dict[str, str] = summary.get("channels", {})
    if blf.exists() and not blf.is_file():  # a FIFO would block for ever; a device or directory is no recording
        raise ConfigError(f"{path}: the incident's frames {blf} are not a regular file; the summary is still readable"
                          " with 'rovercan incident'")
    if blf.is_file() and (unsafe := blf_problem(blf)):
        raise ConfigError(f"{path}: the incident's frames {blf} are not read: {unsafe}")
    try:
        with can.BLFReader(blf) as reader:
            frames = [(channels.get(str(msg.channel), str(msg.channel)), msg) for msg in reader]
    except RECORDING_ERRORS as err:
        what = "missing" if isinstance(err, FileNotFoundError) else "a damaged BLF file"
        raise ConfigError(f"{path}: cannot read the incident's frames in {blf}, {what} ({type(err).__name__}:"
                          f" {err}); the summary is still readable with 'rovercan incident'") from err
    for i, (_, msg) in enumerate(frames):
        if problem := frame_problem(msg):
            raise ConfigError(f"{path}: frame {i + 1} of the incident's BLF {blf} is damaged: {problem}")
    return frames


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
