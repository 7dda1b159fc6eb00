"""A streamed set-point's frame is judged once per drive from its PDO plan (frozen), and packed
without a mapping per set-point: its bytes are encode_rpdo's, byte for byte, for any target and
either order of the two objects in the RPDO (and encode_rpdo's own where the RPDO maps more)."""

from __future__ import annotations

import dataclasses
import random

import pytest

from can_config import GENERIC_EDS, load_drive_od
from can_config.objects import OD, DataType, OperationMode
from motor_driver.drive.command.channel import StreamFrame
from motor_driver.protocol.pdo import PdoMap, PdoPlan, encode_rpdo, plan_pdos

INT32 = (-(2**31), 2**31 - 1)
CW = int(OD.CONTROLWORD)


def targets(n: int = 500) -> list[int]:
    rng = random.Random(72)
    return [*INT32, 0, 1, -1, *(rng.randint(*INT32) for _ in range(n))]


def plan_with(*objects: tuple[int, int]) -> PdoPlan:
    """A plan of one RPDO mapping ``objects`` ((index, data type), in that order)."""
    pdo = PdoMap(1, 0x301, 255, tuple((index, 0, dt) for index, dt in objects))
    return PdoPlan((pdo,), (), 1, 0, 1)


@pytest.mark.parametrize("mode", [OperationMode.CYCLIC_SYNC_POSITION, OperationMode.INTERPOLATED_POSITION])
def test_the_generic_drives_stream_frames_are_encode_rpdos(mode: OperationMode) -> None:
    plan = plan_pdos(load_drive_od(GENERIC_EDS, 1), 1)
    target = OD.TARGET_POSITION if mode == OperationMode.CYCLIC_SYNC_POSITION else OD.INTERPOLATION_DATA
    frame = StreamFrame.of(plan, 0x1F, target)
    pdo = plan.rpdo_with(target)
    assert frame.pdo is pdo
    if pdo is None:  # its target goes by SDO: the frame carries the controlword alone
        return
    for counts in targets():
        assert frame.payload(pdo, counts) == encode_rpdo(pdo, {OD.CONTROLWORD: 0x1F, target: counts})


@pytest.mark.parametrize("order", ["controlword first", "target first"])
def test_either_order_in_the_rpdo_packs_as_encode_rpdo(order: str) -> None:
    objects = [(CW, DataType.UNSIGNED16), (int(OD.TARGET_POSITION), DataType.INTEGER32)]
    plan = plan_with(*(objects if order == "controlword first" else objects[::-1]))
    frame = StreamFrame.of(plan, 0x0F, OD.TARGET_POSITION)
    pdo = plan.rpdos[0]
    assert frame.cw_first is (order == "controlword first")
    for counts in targets():
        assert frame.payload(pdo, counts) == encode_rpdo(pdo, {OD.CONTROLWORD: 0x0F, OD.TARGET_POSITION: counts})


def test_an_rpdo_that_maps_more_is_encode_rpdos_own() -> None:
    """No fast packing for a map of more than the two: encode_rpdo decides, as it did before."""
    plan = plan_with((CW, DataType.UNSIGNED16), (int(OD.TARGET_POSITION), DataType.INTEGER32),
                     (int(OD.TARGET_VELOCITY), DataType.INTEGER32))
    frame = StreamFrame.of(plan, 0x0F, OD.TARGET_POSITION)
    assert frame.cw_first is None
    with pytest.raises(KeyError):  # a value for 0x60FF is not a streamed set-point's to give
        frame.payload(plan.rpdos[0], 5)


def test_the_plan_it_is_judged_from_cannot_change() -> None:
    """Judged once per drive: sound only because the plan and its PDOs are frozen values."""
    plan = plan_pdos(load_drive_od(GENERIC_EDS, 1), 1)
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.rpdos = ()  # type: ignore[misc]
    with pytest.raises(dataclasses.FrozenInstanceError):
        plan.rpdos[1].objects = ()  # type: ignore[misc]
