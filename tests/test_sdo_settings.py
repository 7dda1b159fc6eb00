"""Vendor parameters from the config's per-drive ``sdo:`` list are written at boot, in order,
and read back; a bad entry fails the boot naming the object and the abort code."""

from __future__ import annotations

from collections.abc import Callable

import pytest

from can_config import RoverConfig
from can_config.errors import BootError, ConfigError
from motor_driver import MotorDriver
from virtual_can import SimService

from .conftest import make_config

SimFactory = Callable[[RoverConfig], tuple[SimService, RoverConfig]]


def test_the_sdo_list_is_written_at_boot_in_order_and_checked(sim_factory: SimFactory) -> None:
    sim, cfg = sim_factory(make_config(1, sdo=[{"index": 0x6065, "value": 1234},  # following-error window
                                               {"index": 0x6065, "value": 4321},  # the later entry wins
                                               {"index": 0x6066, "sub": 0, "value": 25, "check": False}]))
    with MotorDriver(cfg).start() as driver:
        drive = driver.drive("joint1")
        assert drive.sdo.read_value(0x6065) == 4321 and drive.sdo.read_value(0x6066) == 25
    runner = sim.simulators["can0"]
    assert runner.call(lambda: runner.drive(1).store.get(0x6065, 0)) == 4321  # on the drive itself


@pytest.mark.parametrize(("entry", "says"), [
    ({"index": 0x2345, "value": 1, "size": 4}, r"boot step 'sdo settings' failed at 0x2345:0: .*0x06020000"),
    ({"index": 0x2345, "value": 1}, r"sdo setting 0x2345:0 is not in the drive's EDS; give its size"),
    ({"index": 0x607A, "value": 1}, r"sdo setting 0x607A:0 is refused: it is a motion target"),
    ({"index": 0x1016, "sub": 1, "value": 0}, r"is refused: it is how the drive watches the host's heartbeat"),
    # read at boot before the settings: written after, the scale and every limit in degrees would be stale
    ({"index": 0x6091, "sub": 1, "value": 2}, r"sdo setting 0x6091:1 is refused: it sets the drive's units"),
    ({"index": 0x6065, "value": -1}, r"value -1 does not fit the object"),
])
def test_a_bad_sdo_entry_fails_the_boot_naming_the_object(sim_factory: SimFactory, entry: dict[str, int],
                                                          says: str) -> None:
    _, cfg = sim_factory(make_config(1, sdo=[entry]))
    with pytest.raises(BootError, match=says):
        MotorDriver(cfg).start()


@pytest.mark.parametrize(("entry", "says"), [
    ({"index": "0x6065", "value": 1}, r"drives\[0\]\.sdo\[0\]\.index: got '0x6065'"),
    ({"index": 0x6065}, r"drives\[0\]\.sdo\[0\]\.value: missing"),
    ({"index": 0x6065, "value": float("nan")}, r"drives\[0\]\.sdo\[0\]\.value: got nan"),
    ({"index": 0x6065, "value": 1, "size": 3}, r"drives\[0\]\.sdo\[0\]\.size: got 3; expected 1, 2, 4 or 8"),
    ({"index": 0x6065, "value": 1, "subindex": 0},
     r"drives\[0\]\.sdo\[0\]\.subindex: unknown key\. Did you mean 'index'\? Allowed keys: index, sub,"),
])
def test_a_bad_sdo_entry_in_the_config_is_named(entry: dict[str, object], says: str) -> None:
    with pytest.raises(ConfigError, match=says):
        make_config(1, sdo=[entry])


def test_every_object_the_drives_units_are_read_from_is_protected() -> None:
    """The scale (and so every limit in degrees and Nm) comes from these objects, read at boot:
    no tool, service or config setting writes one after that."""
    from motor_driver.drive import protected_reason
    from motor_driver.protocol.units import UNIT_OBJECTS

    for index, _ in UNIT_OBJECTS:
        assert "units" in (protected_reason(index) or ""), hex(index)
