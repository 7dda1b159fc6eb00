"""One line per event at the level it deserves: a maxon EPOS4 (its real EDS, its rpm velocity
unit) boots, enables and closes without a WARNING; its normal units are said at INFO, once."""

from __future__ import annotations

import logging

import pytest

from can_config import parse_config, with_bus_overrides
from motor_driver import MotorDriver
from virtual_can import SimService

from .conftest import SHARED_EDS, requires_shared


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
