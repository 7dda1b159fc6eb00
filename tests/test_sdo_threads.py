"""SDO transfers of one driver are serialised by a lock of the project's own, one per node,
whatever thread asks: canopen's SdoClient has none, and 8 threads reading at once saw 71 % of
their reads fail (the answers went to each other's requests)."""

from __future__ import annotations

import threading
from collections.abc import Callable

from can_config import RoverConfig
from motor_driver import MotorDriver
from virtual_can import SimService

from .conftest import make_config


def test_eight_threads_reading_one_drive_at_once_all_get_their_values(
        driver_factory: Callable[[RoverConfig], tuple[SimService, MotorDriver]]) -> None:
    # eight readers queue at the lock: on a busy machine one transfer's wait passed 4 x 0.5 s
    _, driver = driver_factory(make_config(1, sdo_timeout_ms=2000))
    drive = driver.drive("joint1")
    start = threading.Barrier(8)
    errors: list[BaseException] = []
    values: list[tuple[int, object]] = []

    def reader(index: int) -> None:
        start.wait()
        for _ in range(15):
            try:
                values.append((index, drive.sdo.read_value(index)))
            except BaseException as err:
                errors.append(err)

    objects = [0x1000, 0x6502, 0x6064, 0x6041, 0x6061, 0x1017, 0x6065, 0x6060]
    threads = [threading.Thread(target=reader, args=(index,)) for index in objects]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join(60.0)
    assert not errors, errors[:3]
    assert len(values) == 8 * 15
    by_index = {index: {v for i, v in values if i == index} for index in objects}
    assert by_index[0x1000] == {0x00020192}  # each read got its own object's answer
    assert by_index[0x1017] == {int(driver.config.drives[0].heartbeat_period_s * 1000)}
