"""Every CLI input is checked where it is read: bad numbers, files that are not what they claim,
duplicate YAML keys. Each is refused with its name, the allowed range or form, and exit 2,
before any bus is opened (so nothing moves)."""

from __future__ import annotations

import argparse
import signal
import subprocess
import sys
from pathlib import Path

import can
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from can_config import GENERIC_EDS, load_config
from can_config.errors import ConfigError
from rovercan.cli import build_parser, main

from .conftest import REPO, rovercan_cli, wait_for
from .test_host_loss import statusword_enabled, statusword_tpdo
from .test_sim_cli import free_port


def numeric_arguments() -> list[tuple[str, argparse.Action, list[str]]]:
    """(command, action, the positionals before it) for every number the CLI reads."""
    found = []
    sub = next(a for a in build_parser()._actions if isinstance(a, argparse._SubParsersAction))
    for command, parser in sub.choices.items():
        before: list[str] = []
        for action in parser._actions:
            bounds = getattr(action.type, "bounds", None)
            if bounds is not None:
                found.append((command, action, list(before)))
            if not action.option_strings:  # a positional: what comes before the next one
                before.append(action.choices[0] if action.choices else "1")  # type: ignore[index]
    return found


NUMBERS = numeric_arguments()


def test_every_number_the_cli_reads_is_range_checked() -> None:
    names = {(c, a.dest) for c, a, _ in NUMBERS}
    for expected in [("jog", "seconds"), ("jog", "velocity"), ("move", "degrees"), ("move", "gear_ratio"),
                     ("scan", "listen"), ("enable", "hold"), ("step-test", "step"), ("audit", "seconds"),
                     ("demo", "duration"), ("sim", "status_period"), ("can-up", "bitrate")]:
        assert expected in names, expected
    plain = [(c, a.dest) for c, p in build_parser()._subparsers._group_actions[0].choices.items()  # type: ignore[union-attr]
             for a in p._actions if a.type in (float, int) and not a.dest.endswith("bitrate")]
    assert plain == [("sdo", "size")], plain  # --size has choices (1, 2, 4); *bitrate: python-can's bus arguments


def bad_value(bounds: tuple[float, float, bool], draw_float: float, kind: int) -> str:
    low, high, nonzero = bounds
    if kind == 0:
        return ["nan", "inf", "+inf", "NaN", "infinity", "1e999"][int(abs(draw_float)) % 6]
    if kind == 1:
        return ["abc", "", "1,5", "0x", "--", "1..2"][int(abs(draw_float)) % 6]
    if kind == 2 and nonzero and low <= 0 <= high:
        return "0"
    return repr(high + 1 + abs(draw_float)) if draw_float >= 0 else repr(low - 1 - abs(draw_float))


@settings(max_examples=300, deadline=None)
@given(st.sampled_from(NUMBERS), st.floats(-1e9, 1e9, allow_nan=False), st.integers(0, 3))
def test_a_bad_number_names_the_argument_and_the_range_and_exits_2(
        number: tuple[str, argparse.Action, list[str]], draw_float: float, kind: int) -> None:
    command, action, before = number
    value = bad_value(action.type.bounds, draw_float, kind)  # type: ignore[union-attr]
    if value == "--":
        return  # argparse's own separator
    argv = [command, *before, action.option_strings[0], value] if action.option_strings else [command, *before, value]
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2


def run(*args: str, timeout: float = 30) -> subprocess.CompletedProcess[str]:
    return rovercan_cli(*args, timeout=timeout)


@pytest.mark.parametrize(("args", "says"), [
    (["move", "1", "-inf"], "-inf is not a finite number"),
    (["move", "1", "-NaN"], "-NaN is not a finite number"),
    (["jog", "1", "10", "--for", "nan"], "argument --for: 'nan' is not a finite number; give one in 0.01..3600"),
    (["jog", "1", "10", "--for", "-1"], "argument --for: -1 is out of range 0.01..3600"),
    (["scan", "--listen", "nan"], "argument --listen: 'nan' is not a finite number"),
    (["enable", "1", "--hold", "nan"], "argument --hold: 'nan' is not a finite number"),
    (["move", "1", "45", "--gear-ratio", "1e-300"], "argument --gear-ratio: 1e-300 is out of range 0.001..1e+06"),
    (["step-test", "1", "--step", "0"], "argument --step: 0 is out of range -3600..3600, and not 0"),
])
def test_the_reported_bad_numbers_are_refused_before_any_bus(args: list[str], says: str) -> None:
    result = run(*args)
    assert result.returncode == 2 and says in result.stderr, result.stderr
    assert "Traceback" not in result.stderr


def test_a_negative_number_in_exponent_form_is_a_number_not_an_option() -> None:
    result = run("move", "1", "-1e3", "--gear-ratio", "1e-300")  # reaches --gear-ratio: -1e3 was read
    assert result.returncode == 2 and "--gear-ratio" in result.stderr, result.stderr


@pytest.fixture
def bad_files(tmp_path: Path) -> dict[str, Path]:
    files = {"binary": tmp_path / "binary.yaml", "utf16": tmp_path / "utf16.yaml", "latin1": tmp_path / "latin1.yaml"}
    files["binary"].write_bytes(bytes(range(256)))
    files["utf16"].write_text("buses: []\n", encoding="utf-16")
    files["latin1"].write_bytes("drives: [{name: r\xe9gua}]\n".encode("latin-1"))
    return files


@pytest.mark.parametrize(("kind", "says"), [("binary", "is a binary file, not text"), ("utf16", "is UTF-16 text"),
                                            ("latin1", "is not UTF-8 text (byte 0xE9 at offset")])
def test_binary_and_non_utf8_files_are_refused_by_name(bad_files: dict[str, Path], kind: str, says: str) -> None:
    path = bad_files[kind]
    trc = path.with_suffix(".trc")
    trc.write_bytes(path.read_bytes())
    port = str(free_port())
    for args in (["plan", "--config", str(path)], ["sim", "--scenario", str(path), "--port", port],
                 ["decode", str(trc)], ["replay", str(trc), "-i", "virtual", "-c", "rovercan-test"]):
        result = run(*args)
        assert result.returncode == 2 and f"{path if 'trc' not in ' '.join(args) else trc}: " in result.stderr \
            and says in result.stderr, (args, result.stderr)
        assert "Traceback" not in result.stderr and "python-can arguments" not in result.stdout, args


def test_recordings_of_an_unknown_format_are_refused_before_the_bus_opens(tmp_path: Path) -> None:
    yaml_file = tmp_path / "rover.yaml"
    yaml_file.write_text("steps: []\n")
    result = run("decode", str(yaml_file))
    assert result.returncode == 2 and ".yaml is not a recording format python-can reads" in result.stderr
    result = run("record", str(tmp_path / "x.xyz"), "-i", "socketcand", "-c", "can0", "--bus-kwargs",
                 "host=127.0.0.1", "port=1")
    assert result.returncode == 2 and ".xyz is not a format python-can records" in result.stderr, result.stderr
    assert "not properly shut down" not in result.stderr and "not reachable" not in result.stderr
    candump = tmp_path / "trace.txt"
    candump.write_text("(1.000000) can0 701#05\n(1.010000) can0 181#3702\n")
    result = run("decode", str(candump))
    assert result.returncode == 0 and "heartbeat" in result.stdout.lower(), result.stdout


@pytest.mark.parametrize(("args", "name", "what"), [(["step-test", "1", "--step", "10", "--out"], "x", "--out"),
                                                    (["record"], "x.asc", "recording"),
                                                    (["record"], "x.mcap", "recording")])
def test_an_output_path_that_cannot_be_written_is_refused_before_the_bus_opens(
        tmp_path: Path, args: list[str], name: str, what: str) -> None:
    """``step-test --out afile/x`` enabled the drive, stepped it and then lost the measurement to
    the path (exit 1, "[Errno 17] File exists", the argument unnamed); ``record`` opened the bus
    first too (a review's finding). Refused first, naming the argument: the bus here is a port
    where nothing listens, which the old order reached and said."""
    afile = tmp_path / "afile"
    afile.write_text("")
    target = str(afile / name)
    result = run(*args, target, "-i", "socketcand", "-c", "can0", "--bus-kwargs", "host=127.0.0.1", "port=1")
    assert result.returncode == 2, result.stderr
    assert f"{what} {target}" in result.stderr and "is a file, not a folder" in result.stderr, result.stderr
    assert "not reachable" not in result.stderr and "Traceback" not in result.stderr, result.stderr


def test_a_key_given_twice_in_a_config_is_refused_with_both_lines(tmp_path: Path) -> None:
    config = tmp_path / "rover.yaml"
    config.write_text("buses:\n  - {name: can0, interface: virtual, channel: x}\ndrives:\n"
                      "  - name: a\n    node_id: 1\n    node_id: 2\n")
    with pytest.raises(ConfigError, match=r"rover.yaml: line 6, column 5: not valid YAML: duplicate key 'node_id'"
                                          r" \(first given on line 5\)"):
        load_config(config)
    flow = tmp_path / "flow.yaml"
    flow.write_text("buses: [{name: can0, interface: virtual, channel: x, name: can1}]\ndrives: []\n")
    with pytest.raises(ConfigError, match="duplicate key 'name'"):
        load_config(flow)
    result = run("plan", "--config", str(config))
    assert result.returncode == 2 and "duplicate key 'node_id'" in result.stderr


def test_ctrl_c_during_a_step_test_stops_the_drive_without_a_traceback(tmp_path: Path) -> None:
    port = free_port()
    sim = subprocess.Popen([sys.executable, "-m", "rovercan", "sim", "--port", str(port)], cwd=REPO,
                           stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert sim.stdout is not None and "simulated drive" in sim.stdout.readline()
        proc = subprocess.Popen([sys.executable, "-m", "rovercan", "step-test", "1", "--step", "90", "--seconds", "20",
                                 "--out", str(tmp_path / "step"), "-i", "socketcand", "-c", "can0", "--bus-kwargs",
                                 "host=127.0.0.1", f"port={port}"], cwd=REPO, stdout=subprocess.PIPE,
                                stderr=subprocess.PIPE, text=True)
        # booted and enabled (the drive's statusword TPDO, as the driver maps it, on the bus): the step
        # starts right after the enable, so the Ctrl-C comes during the step test
        cob, offset = statusword_tpdo(GENERIC_EDS, 1)
        with can.Bus(interface="socketcand", channel="can0", host="127.0.0.1", port=port) as listener:
            def enabled() -> bool:
                msg = listener.recv(1.0)
                return msg is not None and msg.arbitration_id == cob and \
                    statusword_enabled(int.from_bytes(msg.data[offset:offset + 2], "little"))
            wait_for(enabled, 60.0, "the step test's drive enabled on the bus")
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=20)
    finally:
        sim.send_signal(signal.SIGTERM)
        sim.wait(10)
    assert proc.returncode == 1 and "stopped by SIGINT" in err and "Traceback" not in err, err


def test_socketcand_without_its_address_and_candump_screen_output_say_what_to_do(tmp_path: Path) -> None:
    """Two messages that were Python's: `-i socketcand` without host and port ("__init__() missing 2
    required positional arguments"), and `decode` of candump's screen output ("too many values
    to unpack")."""
    from .test_cli_generated import PYTHON_ERROR_TEXT

    scan = subprocess.run([sys.executable, "-m", "rovercan", "scan", "-i", "socketcand", "-c", "can0"], cwd=REPO,
                          capture_output=True, text=True, timeout=60)
    assert scan.returncode == 2 and "needs --bus-kwargs host=HOST port=PORT" in scan.stderr
    screen = tmp_path / "screen.txt"
    screen.write_text("  can0  701   [1]  05\n  can0  181   [8]  37 02 00 00 00 00 00 00\n")
    decode = subprocess.run([sys.executable, "-m", "rovercan", "decode", str(screen)], cwd=REPO, capture_output=True,
                            text=True, timeout=60)
    assert decode.returncode == 2 and "candump -L" in decode.stderr
    for err in (scan.stderr, decode.stderr):
        assert not PYTHON_ERROR_TEXT.search(err), err


def test_monitor_beside_a_server_that_sends_no_can_frames_says_so_in_one_line() -> None:
    """A hostile 'socketcand' server: the handshake, then lines that are no CAN frame (a time
    that is no number, an id that is no hex). python-can's client raised ValueError with a
    traceback and failed on the same line at every receive."""
    import socket
    import threading

    from .test_cli_generated import PYTHON_ERROR_TEXT

    server = socket.socket()
    server.bind(("127.0.0.1", 0))
    server.listen(1)
    done = threading.Event()

    def accept() -> None:  # every connection: the bench probes the server first with one of its own
        while True:
            try:
                conn, _ = server.accept()
            except OSError:
                return
            threading.Thread(target=serve, args=(conn,), daemon=True).start()

    def serve(conn: socket.socket) -> None:
        with conn:
            conn.sendall(b"< hi >")
            said = b""
            while b"rawmode" not in said:
                chunk = conn.recv(4096)
                if not chunk:
                    return
                said += chunk
                conn.sendall(b"< ok >")
            done.wait(1.0)  # after python-can's handshake, before the junk
            conn.sendall(b"< frame 123 zz.zz 11 >< frame XYZ 1.5 >")
            done.wait(30.0)

    threading.Thread(target=accept, daemon=True).start()
    try:
        run = subprocess.run([sys.executable, "-m", "rovercan", "monitor", "-i", "socketcand", "-c", "can0",
                              "--bus-kwargs", "host=127.0.0.1", f"port={server.getsockname()[1]}", "--seconds", "5"],
                             cwd=REPO, capture_output=True, text=True, timeout=60)
    finally:
        done.set()
        server.close()
    assert run.returncode == 1, run.stderr
    assert "the bus server sent what is no CAN frame" in run.stderr
    assert "Traceback" not in run.stderr and not PYTHON_ERROR_TEXT.search(run.stderr), run.stderr
