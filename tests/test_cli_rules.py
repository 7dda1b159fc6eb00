"""The CLI's exit-code rule, against `rovercan sim` in another process: 0 done; 1 the bus or a
drive failed or refused; 2 bad usage, a bad config or input, or a command refused before it was
sent. Drive commands never run on a bus nobody named."""

from __future__ import annotations

import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from .conftest import REPO, heard_before_marker, on_the_bus, rovercan_cli, rovercan_sim, wait_for
from .test_sim_cli import free_port


@pytest.fixture(scope="module")
def sim_port() -> Iterator[int]:
    with rovercan_sim("--drives", "2") as port:
        yield port


def run(*args: str) -> subprocess.CompletedProcess[str]:
    return rovercan_cli(*args)


def bus(port: int) -> list[str]:
    return ["-i", "socketcand", "-c", "can0", "--bus-kwargs", "host=127.0.0.1", f"port={port}"]


@pytest.mark.parametrize("args", [["move", "1", "10"], ["jog", "1", "10", "--for", "1"], ["enable", "1"],
                                  ["home", "1"], ["step-test", "1", "--step", "10"], ["disable", "1"]])
def test_a_drive_command_without_a_bus_is_refused_not_run_on_a_virtual_one(args: list[str]) -> None:
    result = run(*args)
    assert result.returncode == 2 and "no bus given: pass -i INTERFACE -c CHANNEL" in result.stderr, result.stderr
    assert "no boot-up" not in result.stderr


def test_nmt_to_a_node_that_is_not_there_fails(sim_port: int) -> None:
    for action in ("start", "stop", "preop", "reset"):
        result = run("nmt", action, "9", *bus(sim_port))
        assert result.returncode == 1 and "node 9: nothing heard from it" in result.stderr, (action, result.stderr)
    for action in ("stop", "start", "preop", "reset", "reset-comm", "start"):
        assert run("nmt", action, "2", *bus(sim_port)).returncode == 0, action
    assert run("nmt", "start", "all", *bus(sim_port)).returncode == 0


def limited_config(tmp_path: Path, port: int) -> Path:
    path = tmp_path / "limited.yaml"
    path.write_text("buses:\n  - {name: can0, interface: socketcand, channel: can0,"
                    f" kwargs: {{host: 127.0.0.1, port: {port}}}}}\n"
                    "drives:\n  - {name: joint1, node_id: 1, joint: limited, min_deg: -90, max_deg: 90,"
                    " counts_per_rev: 4096, max_velocity_deg_s: 360}\n")
    return path


def test_commands_refused_before_they_are_sent_exit_2(sim_port: int, tmp_path: Path) -> None:
    config = str(limited_config(tmp_path, sim_port))
    before = run("sdo", "read", "1", "0x6064", *bus(sim_port), "--json").stdout
    for args, says in ((["move", "1", "120"], "above the upper limit max_deg=90"),
                       (["jog", "1", "500", "--for", "1"], "500"),
                       (["move", "1", "10", "--speed", "1000"], "--speed 1000 deg/s: allowed")):
        result = run(*args, "--config", config)
        assert result.returncode == 2 and says in result.stderr, (args, result.stderr)
        assert "Traceback" not in result.stderr
    assert run("sdo", "read", "1", "0x6064", *bus(sim_port), "--json").stdout == before  # nothing moved
    result = run("sim", "--host", "0.0.0.0", "--port", "0")
    assert result.returncode == 2 and "listens on loopback" in result.stderr


GENERIC = str(REPO / "can_config" / "data" / "generic_cia402.eds")


def test_sdo_write_protection_gives_the_real_reason_and_force_overrides(sim_port: int) -> None:
    for index, reason in (("0x1017", "the driver watches the drive's heartbeat"),
                          ("0x6081", "the speed of every profile move"),
                          ("0x1016:1", "how the drive watches the host's heartbeat"),
                          ("0x1A00:1", "changes the PDO set")):
        result = run("sdo", "write", "1", index, "100", "--eds", GENERIC, *bus(sim_port))
        assert result.returncode == 2 and reason in result.stderr and "--force" in result.stderr, result.stderr
    forced = run("sdo", "write", "1", "0x1017", "250", "--eds", GENERIC, "--force", *bus(sim_port))
    assert forced.returncode == 0 and "forced SDO write of protected 0x1017:0" in forced.stderr, forced.stderr
    assert '"value": 250' in run("sdo", "read", "1", "0x1017", "--eds", GENERIC, "--json", *bus(sim_port)).stdout


@pytest.mark.parametrize(("args", "says"), [
    (["sdo", "write", "1", "0x6065", "abc", "--eds", GENERIC], "value 'abc' for 0x6065:0"),
    (["sdo", "write", "1", "0x6065", "1.5"], "expected a whole number"),
    (["sdo", "write", "1", "0x2000", "70000", "--size", "2"], "does not fit --size 2 bytes"),
    (["sdo", "write", "1", "0x6065", "-1", "--eds", GENERIC], "does not fit 0x6065:0"),
    (["sdo", "read", "1", "0x1018:300"], "sub-index 300 out of range 0..255"),
])
def test_sdo_input_errors_name_the_value_and_the_object(sim_port: int, args: list[str], says: str) -> None:
    result = run(*args, *bus(sim_port))
    assert result.returncode == 2 and says in result.stderr and "Traceback" not in result.stderr, result.stderr


def test_a_wrong_port_is_named_within_the_timeout() -> None:
    port = free_port()
    result = run("scan", "--timeout", "1", "-i", "socketcand", "-c", "can0", "--bus-kwargs", "host=127.0.0.1",
                 f"port={port}")
    assert result.returncode == 1 and f"127.0.0.1:{port} not reachable" in result.stderr
    assert "is the simulator running (rovercan sim)" in result.stderr and "in 1 s" in result.stderr, result.stderr


def test_sdo_and_boot_timeouts_come_from_the_config(tmp_path: Path) -> None:
    """A drive that answers an SDO in 0.7 s is read with sdo_timeout_ms 1000 (the default 500 gives up)."""
    from can_config import load_config, with_bus_overrides
    from can_config.errors import ConfigError
    from motor_driver import MotorDriver
    from virtual_can import SimService

    path = tmp_path / "slow.yaml"
    path.write_text("buses: [{name: can0, interface: socketcand, channel: can0, kwargs: {host: 127.0.0.1, port: 1}}]\n"
                    "drives: [{name: j, node_id: 1, counts_per_rev: 4096, sdo_timeout_ms: 1000,"
                    " boot_timeout_ms: 3000}]\n")
    config = load_config(path)
    assert config.drives[0].sdo_timeout_s == 1.0 and config.drives[0].boot_timeout_s == 3.0
    with SimService.from_config(config, port=0) as sim:
        runner = sim.simulators["can0"]
        with MotorDriver(with_bus_overrides(config, host=sim.host, port=sim.port)).start() as driver:
            runner.call(lambda: setattr(runner.drive(1).faults, "sdo_delay_s", 0.7))
            assert driver.drive("j").sdo_read(0x1000, 0)  # 0.7 s: within 1000 ms
    path.write_text(path.read_text().replace("sdo_timeout_ms: 1000", "sdo_timeout_ms: 5"))
    with pytest.raises(ConfigError, match=r"sdo_timeout_ms.*10"):
        load_config(path)


def test_replay_leaves_commands_out_unless_allowed_and_filters(tmp_path: Path) -> None:
    import can

    from can_config import GENERIC_EDS
    from virtual_can import SimDriveSpec, SimService

    log = tmp_path / "incident.log"
    frames = ["000#0101", "201#0F00", "601#2F60600001000000", "181#3712", "701#05", "080#", "581#4B41600037020000"]
    log.write_text("".join(f"({1.0 + i * 0.001:.6f}) can0 {f}\n" for i, f in enumerate(frames)))
    with SimService([SimDriveSpec(5, GENERIC_EDS, "can0", "other", 4096)], port=0) as sim:
        listener = can.Bus(interface="socketcand", channel="can0", host=sim.host, port=sim.port)
        on_the_bus(sim.server, 1)
        try:
            def replayed(*extra: str) -> tuple[subprocess.CompletedProcess[str], set[int]]:
                result = run("replay", str(log), "--fast", *extra, *bus(sim.port))
                # its connection gone from the server: every frame it sent is on the bus, before the marker
                wait_for(lambda: len(sim.server.clients) == 1, 10.0, "the replay's connection closed")
                heard = heard_before_marker(listener, sim.engine)
                own = (0x705, 0x185, 0x285, 0x385, 0x485)  # the simulated drive's own
                return result, {m.arbitration_id for m in heard if m.arbitration_id not in own}

            result, seen = replayed()
            assert result.returncode == 0 and "3 command frames (NMT, RPDO, SDO requests, LSS) left out" in result.stderr
            assert seen == {0x181, 0x701, 0x080, 0x581}, sorted(map(hex, seen))
            result, seen = replayed("--allow-commands")
            assert result.returncode == 0 and {0x000, 0x201, 0x601} <= seen, sorted(map(hex, seen))
            result, seen = replayed("--filter", "0x700:0x780")
            assert result.returncode == 0 and seen == {0x701}, sorted(map(hex, seen))
            assert run("replay", str(log), "--filter", "zz", *bus(sim.port)).returncode == 2
        finally:
            listener.shutdown()


@pytest.mark.skipif(not (REPO.parent / "shared" / "eds" / "schunk_prl120.eds").is_file(),
                    reason="../shared/eds/schunk_prl120.eds not present (a clone without ../shared)")
def test_a_drive_with_interpolated_position_only_moves_jogs_and_steps_from_the_cli(tmp_path: Path) -> None:
    """The SCHUNK PRL120 lists only homing and interpolated position (0x6502 = 0x60) and has no
    0x6098: move, jog and step-test go through the driver's streaming path; home says why not."""
    import json

    eds = str(REPO.parent / "shared" / "eds" / "schunk_prl120.eds")
    with rovercan_sim("--eds", eds) as port:
        drive = ["--eds", eds, "--counts-per-rev", "4096", *bus(port), "--json"]
        moved = run("move", "1", "30", *drive)
        assert moved.returncode == 0, moved.stderr
        assert json.loads(moved.stdout)["angle_deg"] == pytest.approx(30.0, abs=0.2)
        jogged = run("jog", "1", "-40", "--for", "1", *drive)
        assert jogged.returncode == 0, jogged.stderr
        travelled = json.loads(jogged.stdout)["angle_deg"] - json.loads(moved.stdout)["angle_deg"]
        # the way it was asked, and never faster: 40 deg/s for 1 s of the CLI's clock, its ramps and
        # the IP velocity reading's ripple; how far is the clock's (a starved CLI streams fewer steps)
        assert -48.0 < travelled < 0.0, travelled
        stepped = run("step-test", "1", "--step", "20", "--seconds", "1.5", "--out", str(tmp_path / "s"), *drive)
        assert stepped.returncode == 0, stepped.stderr
        assert json.loads((tmp_path / "s.json").read_text())["steady_state_error_deg"] < 0.3
        homed = run("home", "1", *drive)
        assert homed.returncode == 2 and "this drive has no homing mode (no 0x6098 in its EDS)" in homed.stderr


@pytest.mark.skipif(not (REPO.parent / "shared" / "eds" / "maxon_epos4_module50_5.eds").is_file(),
                    reason="../shared/eds/maxon_epos4_module50_5.eds not present (a clone without ../shared)")
def test_a_wrong_counts_per_rev_is_named_after_a_jog_and_a_move() -> None:
    """EPOS4 reports velocity in rpm (0x60A9), independent of the encoder: told 2048 counts per
    revolution for its 4096, positions read half of what they are while velocities are right."""
    eds = str(REPO.parent / "shared" / "eds" / "maxon_epos4_module50_5.eds")
    with rovercan_sim("--eds", eds) as port:
        for counts, wrong in (("2048", True), ("4096", False)):
            for args in (["jog", "1", "60", "--for", "1.5"], ["move", "1", "90" if wrong else "0"]):
                result = run(*args, "--eds", eds, "--counts-per-rev", counts, *bus(port))
                assert result.returncode == 0, result.stderr
                assert ("counts_per_rev looks wrong" in result.stderr) == wrong, (counts, args, result.stderr)


@pytest.mark.skipif(not (REPO.parent / "shared" / "eds" / "schunk_prl120.eds").is_file(),
                    reason="../shared/eds/schunk_prl120.eds not present (a clone without ../shared)")
def test_each_pdo_warning_is_printed_once() -> None:
    eds = str(REPO.parent / "shared" / "eds" / "schunk_prl120.eds")
    result = run("enable", "1", "--eds", eds, "-i", "virtual", "-c", "rovercan-once", "--timeout", "0.1")
    assert result.stderr.count("0x6061 cannot be PDO-mapped") == 1, result.stderr


def test_the_smaller_cli_cases(sim_port: int, tmp_path: Path) -> None:
    import json

    from rovercan.cli import build_parser

    help_text = run("sim", "--help").stdout
    assert "--bus-kwargs" in help_text and "--bus-bus-kwargs" not in help_text
    parsed = build_parser().parse_args(["sim", "--bus-interface", "virtual", "--bus-channel", "x", "--bus-kwargs",
                                        "receive_own_messages=False"])
    assert parsed.bus_bus_kwargs == {"receive_own_messages": False}  # python-can reads it under its own name
    name = json.loads(run("sdo", "read", "1", "0x1008", *bus(sim_port), "--json").stdout)["value"]
    assert isinstance(name, str) and name.isprintable() and name, name  # the device name, not a 70-digit number
    scan = run("scan", *bus(sim_port))
    assert "node/s" not in scan.stderr and "it/s" not in scan.stderr, scan.stderr
    monitor = run("monitor", "--seconds", "0.5", "--eds", GENERIC, *bus(sim_port))
    assert monitor.returncode == 0, monitor.stderr


def test_monitor_parses_an_eds_once_not_per_node(monkeypatch: pytest.MonkeyPatch) -> None:
    """`monitor --seconds 1 --eds` took 3.5 s: the EDS was parsed for each of the 127 node ids."""
    import argparse

    from rovercan.bench import traffic as bench

    parses: list[int] = []
    real = bench.load_drive_od

    def counting(eds: Path, node_id: int) -> object:
        parses.append(node_id)
        return real(eds, node_id)

    monkeypatch.setattr(bench, "load_drive_od", counting)
    layouts = bench.pdo_layouts_for(argparse.Namespace(config=None, eds=GENERIC))
    assert len(parses) == 1 and 0x181 in layouts and 0x1FF in layouts and 0x27F in layouts


def test_save_keeps_parameters_over_a_reset(sim_port: int) -> None:
    import json

    drive = ["--eds", GENERIC, *bus(sim_port)]
    assert run("sdo", "write", "2", "0x6065", "777", *drive).returncode == 0
    assert run("nmt", "reset", "2", *bus(sim_port)).returncode == 0
    assert '"value": 777' not in run("sdo", "read", "2", "0x6065", *drive, "--json").stdout  # not kept unsaved
    assert run("sdo", "write", "2", "0x6065", "777", *drive).returncode == 0
    saved = run("save", "2", *bus(sim_port), "--json")
    assert saved.returncode == 0, saved.stderr
    assert json.loads(saved.stdout)["answer_ms"] >= 400  # the drive's silence while it writes its flash
    assert run("nmt", "reset", "2", *bus(sim_port)).returncode == 0
    assert '"value": 777' in run("sdo", "read", "2", "0x6065", *drive, "--json").stdout
    missing = run("save", "9", *bus(sim_port))
    assert missing.returncode == 1 and "no answer to the save (0x1010:1)" in missing.stderr


@pytest.mark.skipif(not (REPO.parent / "shared" / "eds" / "maxon_epos4_module50_5.eds").is_file(),
                    reason="../shared/eds/maxon_epos4_module50_5.eds not present (a clone without ../shared)")
def test_a_simulated_epos4_reports_the_identity_of_its_eds() -> None:
    """The EPOS4 file carries vendor, product, revision and name only in [DeviceInfo]."""
    import json

    eds = str(REPO.parent / "shared" / "eds" / "maxon_epos4_module50_5.eds")
    with rovercan_sim("--eds", eds) as port:
        result = run("info", "1", "--eds", eds, *bus(port), "--json")
        assert result.returncode == 0, result.stderr
        text = result.stdout
    info = json.loads(text)
    flat = json.dumps(info)
    assert "0x000000FB" in flat and "0x61500000" in flat and "0x01500000" in flat, flat[:800]
    assert "EPOS4 Module 50/5" in flat
