"""One line per event at the level it deserves: a maxon EPOS4 (its real EDS, its rpm velocity
unit) boots, enables and closes without a WARNING; its normal units are said at INFO, once. The
canopen library's records reach our logging at their level, but its abort of a transfer this
driver ended on purpose is DEBUG (motor_driver/bus/library_log.py); the demo prints each line once."""

from __future__ import annotations

import logging
import os
import subprocess
import sys
from collections.abc import Callable

import pytest

from can_config import RoverConfig, parse_config, with_bus_overrides
from can_config.errors import SdoTimeoutError
from motor_driver import MotorDriver
from virtual_can import SimService

from .conftest import REPO, SHARED_EDS, make_config, requires_ros, requires_shared


@requires_shared
def test_an_epos4_boot_logs_no_warning(caplog: pytest.LogCaptureFixture) -> None:
    eds = SHARED_EDS / "maxon_epos4_module50_5.eds"
    cfg = parse_config({"buses": [{"name": "can0", "interface": "socketcand", "channel": "can0"}],
                        "drives": [{"name": "wheel", "node_id": 1, "eds": str(eds), "counts_per_rev": 4096}]})
    with SimService.from_config(cfg, port=0) as sim:
        caplog.set_level(logging.INFO)
        with MotorDriver(with_bus_overrides(cfg, host="127.0.0.1", port=sim.port)).start() as driver:
            driver.drive("wheel").enable()
            driver.drive("wheel").set_velocity(30.0)
        ours = [r for r in caplog.records if r.name.startswith(("motor_driver", "can_config"))]
    warnings = [r.getMessage() for r in ours if r.levelno >= logging.WARNING]
    assert warnings == []
    units = [r.getMessage() for r in ours if "0x60A9" in r.getMessage() or "rpm" in r.getMessage().lower()]
    assert len(units) <= 1 and all(r.levelno == logging.INFO for r in ours if r.getMessage() in units)


def test_an_sdo_timeout_this_driver_aborts_is_debug_not_error(
        driver_factory: Callable[[RoverConfig], tuple[SimService, MotorDriver]], caplog: pytest.LogCaptureFixture) -> None:
    """A lost drive's SDO read times out and canopen's client aborts the transfer (0x05040000): the
    driver's own doing, said by its SdoTimeoutError; canopen's "Transfer aborted by client" line is
    DEBUG (canopen logs it at ERROR), and absent where canopen logs from INFO."""
    sim, driver = driver_factory(make_config(1, sdo_timeout_ms=100))
    runner = sim.simulators["can0"]
    runner.call(lambda: setattr(runner.drive(1).faults, "unplugged", True))
    for level in (logging.INFO, logging.DEBUG):
        caplog.clear()
        caplog.set_level(level, logger="canopen")
        caplog.set_level(level, logger="canopen.sdo.client")  # a CLI run in this worker may have quieted it
        with pytest.raises(SdoTimeoutError):
            driver.drive("joint1").sdo_read(0x1000, 0)
        aborts = [r for r in caplog.records if r.getMessage().startswith("Transfer aborted by client")]
        if level == logging.INFO:
            assert aborts == []
        else:
            assert aborts and all(r.levelno == logging.DEBUG and r.levelname == "DEBUG" for r in aborts)
            assert "0x05040000" in aborts[0].getMessage()


@requires_ros
def test_canopen_reaches_the_ros_log_at_its_own_level(monkeypatch: pytest.MonkeyPatch) -> None:
    """Bridged to a node's rclpy logger: canopen's INFO and ERROR at their level, its abort of this
    driver's own transfer not at all (DEBUG, below the node's INFO)."""
    import rclpy

    from motor_driver.bus import connect  # noqa: F401  (installs the canopen filter, as the driver does)
    from nodes.process.logbridge import bridge_core_logging, unbridge

    # an in-process CLI run earlier in this worker may have quieted canopen's SDO logger (its
    # --verbose 0): what is tested is the filter and the bridge, so the logger passes its records
    monkeypatch.setattr(logging.getLogger("canopen.sdo.client"), "level", logging.NOTSET)

    context = rclpy.Context()
    rclpy.init(context=context)
    node = rclpy.create_node("log_probe", context=context)
    handler = bridge_core_logging(node)
    forwarded: list[tuple[int, str]] = []
    monkeypatch.setattr(handler, "emit", lambda record: forwarded.append((record.levelno, record.getMessage())))
    try:
        logging.getLogger("canopen.sdo.client").error("Transfer aborted by client with code 0x%08X", 0x05040000)
        logging.getLogger("canopen.sdo.client").error("Block transfer was not finished")
        logging.getLogger("canopen.network").info("a canopen INFO line")
    finally:
        unbridge(handler)
        node.destroy_node()
        rclpy.shutdown(context=context)
    assert forwarded == [(logging.ERROR, "Block transfer was not finished"), (logging.INFO, "a canopen INFO line")]


@requires_ros
def test_the_demo_prints_each_driver_line_once() -> None:
    """rclpy prints the driver's bridged records; the CLI's console handler printed them again
    (every line twice in ``rovercan demo``)."""
    env = {k: v for k, v in os.environ.items() if k not in ("ROS_AUTOMATIC_DISCOVERY_RANGE", "ROVERCAN_REALTIME")}
    result = subprocess.run([sys.executable, "-m", "rovercan", "demo", "--duration", "3"], cwd=REPO,
                            capture_output=True, text=True, timeout=120, env=env, check=False)
    out = result.stdout + result.stderr
    assert result.returncode == 0, out
    for event in ("booted: 4 RPDOs", "armed (Operation Enabled)", "every 10.0 ms by the daemon's timer"):
        assert sum(event in line for line in out.splitlines()) == 1, (event, out)
