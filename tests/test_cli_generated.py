"""Every bench subcommand with generated argument lists (valid, invalid, boundary), against a
simulator: the exit code is 0, 1 or 2, nothing escapes as a traceback, and no drive is left
enabled. The commands run in this process (``rovercan.cli.main``, the same code path as the
console script, without a Python start per call) so that 500 invocations take about two
minutes; tests/test_cli_bench.py runs them as real subprocesses."""

from __future__ import annotations

import io
import logging
import re
from collections.abc import Callable, Iterator
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path
from typing import Any

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from can_config import GENERIC_EDS
from rovercan.cli import main
from virtual_can import SimDriveSpec, SimService

from .conftest import REPO

NODE = st.sampled_from(["1", "2", "1", "2", "1", "0", "128", "abc", "0x1", "-1", "9"])  # 9: not on the bus
NUMBER = st.one_of(st.sampled_from(["0", "-1", "nan", "inf", "-inf", "1e309", "abc", "", "0.5", "10", "-10", "90",
                                    "1000", "1e-300", "179.99", "-179.99", "360"]),
                   st.floats(-1e4, 1e4, allow_nan=False).map(repr))
SECONDS = st.sampled_from(["0.1", "0.2", "0", "-1", "nan", "0.05", "0.3", "1e9"])
INDEX = st.sampled_from(["0x1000", "1018:1", "0x6064", "0x1018:300", "zz", "0x10000", "6065", "0x1017", "0x2345",
                         "0x607A", "0x1008", "1A00:0", ":", "0x6041:0x1"])
VALUE = st.sampled_from(["1", "abc", "-1", "0x7fffffff", "1e3", "99999999999", "250", "0", ""])
#: --look of the commands that may reset: mostly short (each default look is 1.1 s), some refused
LOOK = st.sampled_from([["--look", "0.2"], ["--look", "0.2"], ["--look", "0.2"], ["--look", "0"], ["--look", "nan"], []])


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[SimService, Path]]:
    with SimService([SimDriveSpec(1, GENERIC_EDS, "can0", "a", 4096), SimDriveSpec(2, GENERIC_EDS, "can0", "b", 4096)],
                    port=0) as service:
        tmp = tmp_path_factory.mktemp("generated")
        config = tmp / "rover.yaml"
        config.write_text("buses: [{name: can0, interface: socketcand, channel: can0,"
                          f" kwargs: {{host: 127.0.0.1, port: {service.port}}}}}]\n"
                          "drives:\n  - {name: a, node_id: 1, counts_per_rev: 4096, joint: limited, min_deg: -90,"
                          " max_deg: 90}\n  - {name: b, node_id: 2, counts_per_rev: 4096}\n")
        log = tmp / "trace.log"
        log.write_text("(1.000000) can0 701#05\n(1.010000) can0 181#3712\n(1.020000) can0 000#0101\n")
        yield service, tmp


def bus_args(draw: Callable[[Any], Any], port: int) -> list[str]:
    kind = draw(st.sampled_from(["sim", "sim", "sim", "sim hex", "none", "wrong port", "junk port"]))
    if kind == "none":
        return []
    text = {"sim": str(port), "sim hex": hex(port), "wrong port": "1"}.get(kind) or draw(
        st.sampled_from(["0xZZ", "-1", "70000", "", "1e3", "0x", "port"]) | st.text(max_size=6))
    return ["-i", "socketcand", "-c", "can0", "--bus-kwargs", "host=127.0.0.1", f"port={text}", "--timeout", "0.2"]


@st.composite
def invocation(draw: Callable[[Any], Any], port: int, tmp: str) -> list[str]:
    config = f"{tmp}/rover.yaml"
    drive = draw(st.sampled_from([["--eds", str(GENERIC_EDS), "--counts-per-rev", "4096"], ["--config", config],
                                  ["--counts-per-rev", "0"], ["--gear-ratio", "0"], []]))
    command = draw(st.sampled_from(["scan", "info", "sdo", "nmt", "enable", "disable", "fault-reset", "home",
                                    "move", "jog", "monitor", "record", "replay", "decode", "step-test",
                                    "safety-check", "plan", "can-up"]))
    bus = [] if "--config" in drive and draw(st.booleans()) else bus_args(draw, port)
    json_flag = draw(st.sampled_from([[], ["--json"]]))
    if command == "scan":
        return [command, "--listen", draw(SECONDS), *bus, *json_flag]
    if command == "info":
        return [command, draw(NODE), *bus, *json_flag]
    if command == "sdo":
        action = draw(st.sampled_from(["read", "write"]))
        value = [draw(VALUE)] if action == "write" else []
        extra = draw(st.sampled_from([[], ["--eds", str(GENERIC_EDS)], ["--size", "2"], ["--force"]]))
        return [command, action, draw(NODE), draw(INDEX), *value, *extra, *bus, *json_flag]
    if command == "nmt":
        return [command, draw(st.sampled_from(["start", "stop", "preop", "reset", "reset-comm"])),
                draw(st.sampled_from(["1", "2", "all", "9", "0", "x"])), *draw(LOOK), *bus]
    if command in ("enable", "disable", "fault-reset", "home"):
        hold = ["--hold", draw(SECONDS)] if command == "enable" and draw(st.booleans()) else []
        return [command, draw(NODE), *hold, *drive, *draw(LOOK), *bus, *json_flag]
    if command == "move":
        speed = ["--speed", draw(NUMBER)] if draw(st.booleans()) else []
        return [command, draw(NODE), draw(NUMBER), *speed, *drive, *draw(LOOK), *bus, *json_flag]
    if command == "jog":
        return [command, draw(NODE), draw(NUMBER), "--for", draw(SECONDS), *drive, *draw(LOOK), *bus, *json_flag]
    if command in ("monitor", "record"):
        target = [f"{tmp}/out{draw(st.sampled_from(['.log', '.asc', '.xyz', '']))}"] if command == "record" else []
        return [command, *target, "--seconds", draw(st.sampled_from(["0.1", "0.2", "-1", "nan"])), *bus]
    if command in ("replay", "decode"):
        file = draw(st.sampled_from([f"{tmp}/trace.log", f"{tmp}/rover.yaml", f"{tmp}/missing.trc", str(REPO)]))
        extra = draw(st.sampled_from([[], ["--fast"], ["--allow-commands", "--fast"], ["--filter", "0x700:0x780"],
                                      ["--filter", "zz"]])) if command == "replay" else []
        return [command, file, *extra, *(bus if command == "replay" else [])]
    if command == "step-test":
        return [command, draw(NODE), "--step", draw(NUMBER), "--seconds", draw(SECONDS), "--out", f"{tmp}/step",
                *drive, *draw(LOOK), *bus, *json_flag]
    if command == "safety-check":
        return [command, *drive, *bus, "--listen", draw(SECONDS), *json_flag]
    if command == "plan":
        return [command, "--config", draw(st.sampled_from([config, f"{tmp}/trace.log", f"{tmp}/none.yaml"])),
                *json_flag]
    return [command, draw(st.sampled_from(["can0", "vcan0", "can0;reboot", ""])), "--dry-run",
            *draw(st.sampled_from([[], ["--bitrate", "500000"], ["--bitrate", "0"], ["--config", config]]))]


def run_in_process(argv: list[str]) -> tuple[int, str]:
    err = io.StringIO()
    handler = logging.StreamHandler(err)
    logging.getLogger().addHandler(handler)
    try:
        with redirect_stdout(io.StringIO()), redirect_stderr(err):
            try:
                code = main(argv)
            except SystemExit as exit_:  # argparse
                code = int(exit_.code or 0)
    finally:
        logging.getLogger().removeHandler(handler)
    return code, err.getvalue()


#: Python's own words for an error, which a user cannot act on: "TypeError: ...", "__init__() missing
#: 1 required positional argument", "too many values to unpack", "could not convert string to float".
PYTHON_ERROR_TEXT = re.compile(r"\b[A-Z]\w*(Error|Exception): |__init__\(\)|positional argument|values to unpack|"
                               r"could not convert string")


def test_every_subcommand_with_generated_arguments(sim: tuple[SimService, Path]) -> None:
    service, tmp = sim
    runner = service.simulators["can0"]
    seen: dict[int, int] = {}

    @settings(max_examples=500, deadline=None, database=None,
              suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
    @given(invocation(service.port, str(tmp)))
    def one(argv: list[str]) -> None:
        code, err = run_in_process(argv)
        seen[code] = seen.get(code, 0) + 1
        assert code in (0, 1, 2), (argv, code, err[-2000:])
        assert "Traceback" not in err, (argv, err[-3000:])
        assert not PYTHON_ERROR_TEXT.search(err), (argv, err[-3000:])  # the user's words, not Python's
        enabled = runner.call(lambda: [n for n in (1, 2) if runner.drive(n).state.name == "OPERATION_ENABLED"])
        assert not enabled, (argv, enabled, err[-2000:])

    one()
    assert sum(seen.values()) >= 500 and set(seen) == {0, 1, 2}, seen  # every kind of outcome was exercised
