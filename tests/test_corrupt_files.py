"""Damaged files get one line, never a traceback: recordings of every format python-can reads
(truncated, bit-flipped, bytes replaced) through ``decode`` and ``replay``, and flight-recorder
incidents (each JSON field given a wrong type or removed, the JSON or its BLF damaged) through
``incident``, ``incident --scenario`` and ``sim --scenario-from-log``.

The commands run in this process (``rovercan.cli.main``, the console script's code path) so
that an exception outside the project's tree fails the test with its traceback; the exit code
is 0 (the damage left a readable file), 1 (the bus was not there) or 2 with one line on stderr
naming the file."""

from __future__ import annotations

import copy
import functools
import io
import json
import logging
import tempfile
from collections.abc import Callable, Iterator
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path
from typing import Any

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from motor_driver.recording.incident import FORMAT
from rovercan.cli import main

FORMATS = [".asc", ".blf", ".csv", ".db", ".log", ".trc", ".txt"]
#: No bus here: replay reads the whole file first, then fails to connect (exit 1).
NO_BUS = ["-i", "socketcand", "-c", "can0", "--bus-kwargs", "host=127.0.0.1", "port=1", "--timeout", "0.2"]


def frames() -> list[can.Message]:
    out = []
    for i in range(30):
        t = 1_700_000_000.0 + i * 0.01
        out.append(can.Message(timestamp=t, arbitration_id=0x181, data=bytes([0x37, 0x06, i, 0, 0, 0]), channel=1))
        out.append(can.Message(timestamp=t + 0.001, arbitration_id=0x701, data=b"\x05", channel=1))
    out.append(can.Message(timestamp=t + 0.002, arbitration_id=0x1ABCDEF, is_extended_id=True, data=b"\x01\x02",
                           channel=1))
    out.append(can.Message(timestamp=t + 0.003, arbitration_id=0x081, data=bytes.fromhex("1023010000000000"),
                           channel=1))
    out.append(can.Message(timestamp=t + 0.004, arbitration_id=0x701, is_remote_frame=True, dlc=1, channel=1))
    return out


def write_recording(path: Path) -> None:
    writer: can.Listener = can.CanutilsLogWriter(path) if path.suffix == ".txt" else can.Logger(path)
    try:
        for msg in frames():
            writer.on_message_received(msg)
    finally:
        writer.stop()


def cli(*argv: str) -> tuple[int, str]:
    err = io.StringIO()
    with redirect_stdout(io.StringIO()), redirect_stderr(err):
        code = main(list(argv))
    return code, err.getvalue()


def assert_one_clear_line(code: int, stderr: str, path: Path) -> None:
    assert code in (0, 1, 2), (code, stderr)
    if code == 2:
        lines = [line for line in stderr.splitlines() if line.strip()]
        assert len(lines) == 1 and lines[0].startswith("rovercan: "), stderr
        assert path.stem in lines[0], f"the line does not name the file: {lines[0]}"


@functools.cache
def original(suffix: str) -> bytes:
    """A whole recording of the format (a module-level cache, not a fixture: hypothesis would print
    every format's bytes with each failing example)."""
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"whole{suffix}"
        write_recording(path)
        return path.read_bytes()


@pytest.fixture(autouse=True)
def quiet() -> Iterator[None]:
    yield
    logging.getLogger().handlers.clear()  # main() sets up logging per call


def test_each_whole_recording_decodes(tmp_path: Path) -> None:
    """The base of the damage: every format, whole, decodes (so a 2 below is the damage's)."""
    for suffix in FORMATS:
        path = tmp_path / f"whole{suffix}"
        path.write_bytes(original(suffix))
        code, stderr = cli("decode", str(path))
        assert code == 0, (suffix, stderr)


@st.composite
def damage(draw: Callable[[Any], Any], raw: bytes) -> bytes:
    kind = draw(st.sampled_from(["truncate", "flip", "replace", "insert"]))
    if kind == "truncate":
        return raw[:draw(st.integers(0, max(0, len(raw) - 1)))]
    data = bytearray(raw)
    for _ in range(draw(st.integers(1, 12))):
        at = draw(st.integers(0, len(data) - 1))
        if kind == "flip":
            data[at] ^= 1 << draw(st.integers(0, 7))
        elif kind == "replace":
            data[at] = draw(st.integers(0, 255))
        else:
            data[at:at] = draw(st.binary(min_size=1, max_size=8))
    return bytes(data)


@settings(max_examples=250, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_a_damaged_recording_gets_one_line(tmp_path: Path, data: st.DataObject) -> None:
    suffix = data.draw(st.sampled_from(FORMATS))
    path = tmp_path / f"damaged{suffix}"
    path.write_bytes(data.draw(damage(original(suffix))))
    command = data.draw(st.sampled_from([["decode", str(path)], ["decode", str(path), "--json"],
                                         ["replay", str(path), "--fast", *NO_BUS]]))
    assert_one_clear_line(*cli(*command), path)


def test_an_unreadable_format_says_what_is_missing(tmp_path: Path) -> None:
    path = tmp_path / "trace.mf4"
    path.write_bytes(b"MDF     4.10    ")
    code, stderr = cli("decode", str(path))
    assert code == 2 and "trace.mf4" in stderr and len(stderr.strip().splitlines()) == 1, stderr


# ------------------------------------------------------------------------------ incidents
def incident(tmp: Path) -> tuple[Path, dict[str, Any]]:
    """A whole incident as the flight recorder writes it: summary and BLF."""
    blf = tmp / "20261125-101010-000-emcy-left.blf"
    with can.BLFWriter(blf) as writer:
        for msg in frames():
            writer.on_message_received(msg)
    t = 1_700_000_000.3
    summary = {
        "format": FORMAT, "kind": "emcy", "time": "2026-11-25T10:10:10", "t": t,
        "events": [{"kind": "emcy", "t": t, "bus": "can0", "node": 1, "drive": "left", "code": 0x2310,
                    "text": "continuous over-current"}],
        "window_s": [-0.3, 0.1], "frames": len(frames()), "channels": {"1": "can0"}, "bus_channels": {"can0": "can0"},
        "drives": [{"name": "left", "bus": "can0", "node_id": 1}], "config": None, "blf": blf.name, "png": None,
        "states": {},
    }
    return blf.with_suffix(".json"), summary


WRONG: st.SearchStrategy[Any] = st.sampled_from([None, "x", "", 1.5, -1, 0, 10**30, True, [], {}, [1], {"a": 1}, "../../etc/passwd",
                         float("nan"), [None], [{}]])


def paths(summary: dict[str, Any]) -> list[tuple[str | int, ...]]:
    out: list[tuple[str | int, ...]] = [(key,) for key in summary]
    out += [("events", 0, key) for key in summary["events"][0]]
    out += [("drives", 0, key) for key in summary["drives"][0]]
    out += [("window_s", 0), ("window_s", 1), ("channels", "1"), ("bus_channels", "can0"), ("events", 0),
            ("drives", 0)]
    return out


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(data=st.data())
def test_a_damaged_incident_gets_one_line(tmp_path: Path, data: st.DataObject) -> None:
    json_path, whole = incident(tmp_path)
    summary = copy.deepcopy(whole)
    kind = data.draw(st.sampled_from(["wrong type", "wrong type", "removed", "json damaged", "blf damaged"]))
    text = None
    if kind in ("wrong type", "removed"):
        where = data.draw(st.sampled_from(paths(whole)))
        parent: Any = summary
        for step in where[:-1]:
            parent = parent[step]
        if kind == "removed" and isinstance(parent, dict):
            del parent[where[-1]]
        else:
            parent[where[-1]] = data.draw(WRONG)
    elif kind == "json damaged":
        text = data.draw(damage(json.dumps(summary, indent=1).encode())).decode("utf-8", "replace")
    else:
        blf = json_path.with_suffix(".blf")
        blf.write_bytes(data.draw(damage(blf.read_bytes())))
    json_path.write_text(text if text is not None else json.dumps(summary))
    command = data.draw(st.sampled_from([["incident", str(json_path)], ["incident", str(json_path), "--json"],
                                         ["incident", str(json_path), "--scenario"],
                                         ["incident", str(json_path.with_suffix(".blf")), "--scenario"]]))
    assert_one_clear_line(*cli(*command), json_path)


def test_a_whole_incident_reads(tmp_path: Path) -> None:
    json_path, summary = incident(tmp_path)
    json_path.write_text(json.dumps(summary))
    code, stderr = cli("incident", str(json_path))
    assert code == 0, stderr
    code, stderr = cli("incident", str(json_path), "--scenario")
    assert code == 0, stderr


@pytest.mark.parametrize("kind", ["missing", "folder"])
def test_an_incident_that_cannot_be_read_is_said_so_not_called_a_bad_summary(tmp_path: Path, kind: str) -> None:
    """A missing .json (or a folder) was "not an incident summary (it nests deeper, or holds
    longer numbers, ...)": the file reader's own error, a ValueError too, was caught as the
    parser's (a review's finding)."""
    path = tmp_path / "nosuch.json"
    if kind == "folder":
        path.mkdir()
    for argv in (["incident", str(path)], ["sim", "--scenario-from-log", str(path)]):
        code, err = cli(*argv)
        assert code == 2 and str(path) in err and "nests deeper" not in err, err


def test_a_wrong_typed_field_is_named(tmp_path: Path) -> None:
    json_path, summary = incident(tmp_path)
    summary["events"][0]["code"] = "0x2310"
    json_path.write_text(json.dumps(summary))
    code, stderr = cli("incident", str(json_path))
    assert code == 2
    assert "events[0].code is '0x2310', not int or null" in stderr, stderr


def hostile_files(tmp: Path) -> dict[str, Path]:
    """Files made to hurt a reader that trusts them (issue 39): an sqlite `messages` view that
    never ends, a BLF container that inflates to 64 MiB, a BLF object that claims 3 GB, a config
    with a 5,000-digit number, an incident nested 200,000 deep."""
    import sqlite3
    import struct
    import zlib

    out = {name: tmp / name for name in ("view.db", "bomb.blf", "lie.blf", "bignumber.yaml", "deep.json")}
    with sqlite3.connect(out["view.db"]) as db:
        db.execute("CREATE VIEW messages AS WITH RECURSIVE n(x) AS (SELECT 1 UNION ALL SELECT x + 1 FROM n)"
                   " SELECT x AS ts, 1 AS arbitration_id, 0 AS extended, 0 AS remote, 0 AS error, 0 AS dlc,"
                   " x'' AS data FROM n")
    head = struct.pack("<4sL", b"LOGG", 144) + bytes(136)
    inflated = 64 * 1024 * 1024
    body = struct.pack("<H6xL4x", 2, inflated) + zlib.compress(bytes(inflated), 9)
    bomb = struct.pack("<4sHHLL", b"LOBJ", 16, 1, 16 + len(body), 10) + body
    out["bomb.blf"].write_bytes(head + bomb + bytes(len(bomb) % 4))
    out["lie.blf"].write_bytes(head + struct.pack("<4sHHLL", b"LOBJ", 16, 1, 3_000_000_000, 10) + bytes(32))
    out["bignumber.yaml"].write_text("buses: [{name: can0, interface: socketcand, channel: can0}]\n"
                                     f"drives:\n  - {{name: m, node_id: {'9' * 5000}}}\n")
    out["deep.json"].write_text('{"format": ' + "[" * 200_000 + "]" * 200_000 + "}")
    return out


@pytest.mark.parametrize(("name", "command", "says"), [
    ("view.db", "decode", "is a view, not a table"), ("view.db", "replay", "is a view, not a table"),
    ("bomb.blf", "decode", "inflates past 16 MiB"), ("lie.blf", "decode", "claims 3000000000 bytes"),
    ("bignumber.yaml", "check", "a number of 5000 characters"), ("deep.json", "incident", "nests deeper")])
def test_a_hostile_file_is_one_line_and_read_no_further(tmp_path: Path, name: str, command: str, says: str) -> None:
    """Each is refused before its reader runs away (a view never ends; a bomb or a size lie
    allocates gigabytes; Python's int and JSON parsers raise their own errors): one line, exit 2."""
    path = hostile_files(tmp_path)[name]
    argv = {"decode": ["decode", str(path)], "replay": ["replay", str(path), *NO_BUS],
            "check": ["check", "--config", str(path)], "incident": ["incident", str(path)]}[command]
    code, err = cli(*argv)
    assert_one_clear_line(code, err, path)
    assert says in err, err


def test_an_incident_whose_frames_are_a_fifo_is_refused_not_waited_on(tmp_path: Path) -> None:
    """`incident --scenario` opened the BLF its summary names; a FIFO there blocked for ever."""
    import os

    summary = {"format": FORMAT, "kind": "emcy", "time": "2026-11-25T00:00:00", "t": 1.0,
               "events": [{"kind": "emcy", "t": 1.0, "bus": "can0", "node": 1, "drive": "m", "code": 0x2310,
                           "text": "over-current"}],
               "window_s": [0, 0], "frames": 0, "channels": {"1": "can0"}, "bus_channels": {"can0": "can0"},
               "drives": [{"name": "m", "bus": "can0", "node_id": 1}], "config": None, "blf": "frames.blf",
               "png": None, "states": {}}
    path = tmp_path / "incident.json"
    path.write_text(json.dumps(summary))
    os.mkfifo(tmp_path / "frames.blf")
    code, err = cli("incident", str(path), "--scenario")
    assert_one_clear_line(code, err, path)
    assert code == 2 and "not a regular file" in err, err


def test_an_incident_of_a_hundred_thousand_events_shows_its_ends_and_says_so(tmp_path: Path) -> None:
    """A flapping drive's summary can hold 100,000 events (laying them all out in a table took
    43 s): the table shows the first and last 50 and says how many there are; --json has all."""
    events = [{"kind": "emcy", "t": 1.0 + i * 1e-3, "bus": "can0", "node": 1, "drive": "m", "code": 0x2310,
               "text": "over-current"} for i in range(100_000)]
    summary = {"format": FORMAT, "kind": "emcy", "time": "2026-11-25T00:00:00", "t": 1.0, "events": events,
               "window_s": [0, 0], "frames": 0, "channels": {"1": "can0"}, "bus_channels": {"can0": "can0"},
               "drives": [{"name": "m", "bus": "can0", "node_id": 1}], "config": None, "blf": None, "png": None,
               "states": {}}
    path = tmp_path / "flapping.json"
    path.write_text(json.dumps(summary))
    out = io.StringIO()
    with redirect_stdout(out), redirect_stderr(io.StringIO()):
        assert main(["incident", str(path)]) == 0
    assert out.getvalue().count("0x2310") == 100
    assert "the first and last 50 of 100,000 events; --json gives every one" in out.getvalue()
    full = io.StringIO()
    with redirect_stdout(full), redirect_stderr(io.StringIO()):
        assert main(["incident", str(path), "--json"]) == 0
    assert len(json.loads(full.getvalue())["events"]) == 100_000


@pytest.mark.parametrize("token", [b"'\x80", b"'\n"], ids=["not-utf8", "newline"])
def test_a_database_whose_schema_is_damaged_gets_one_line(tmp_path: Path, token: bytes) -> None:
    """The schema text of a damaged .db need not be UTF-8 nor one line (hypothesis found both:
    a UnicodeDecodeError traceback, and an error of two lines quoting the damaged token)."""
    import sqlite3

    path = tmp_path / "damaged.db"
    with sqlite3.connect(path) as db:
        db.execute("CREATE TABLE messages(ts REAL, xyzzy INTEGER)")
    raw = path.read_bytes()
    assert raw.count(b"xyzzy") == 1
    path.write_bytes(raw.replace(b"xyzzy", b"xy" + token + b"zy"))
    for command in (["decode", str(path)], ["replay", str(path), "--fast", *NO_BUS]):
        code, err = cli(*command)
        assert code == 2, err
        assert_one_clear_line(code, err, path)
