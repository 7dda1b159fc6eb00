"""Nothing a drive says about its units is trusted unbounded (issue 39): every unit and scaling
object is checked against a plausible range before use, and every profile value boot writes is
checked against its object's type first: never 0 (a zero quick-stop deceleration does not
stop), never saturated. Generated objects, then boots against a drive that reports absurd ones."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import canopen
import pytest
from canopen.objectdictionary import ODRecord, ODVariable
from hypothesis import given, settings
from hypothesis import strategies as st

from can_config import RoverConfig, load_config, with_bus_overrides
from can_config.config import GENERIC_EDS
from can_config.errors import BootError, UnitError
from can_config.objects import DataType
from motor_driver import MotorDriver
from motor_driver.protocol.unit_ranges import TYPE_MAX, check_drive_value
from motor_driver.protocol.units import scale_from_objects
from virtual_can import SimService

from .conftest import REPO, make_config

SimFactory = Callable[[RoverConfig], tuple[SimService, RoverConfig]]
U32 = st.integers(0, 2**32 - 1)
SI_CODE = st.builds(lambda prefix, num, den: (prefix & 0xFF) << 24 | num << 16 | den << 8,
                    st.integers(-128, 127), st.sampled_from([0xB4, 0xB5, 0x01]), st.sampled_from([0x03, 0x47, 0x57, 0]))


@st.composite
def unit_objects(draw: st.DrawFn) -> dict[tuple[int, int], int]:
    objects: dict[tuple[int, int], int] = {}
    for index in (0x608F, 0x6091, 0x6092):
        if draw(st.booleans()):
            objects[(index, 1)], objects[(index, 2)] = draw(U32), draw(U32)
    for index in (0x60A8, 0x60A9, 0x60AA):
        if draw(st.booleans()):
            objects[(index, 0)] = draw(SI_CODE)
    if draw(st.booleans()):
        objects[(0x6076, 0)] = draw(U32)
    return objects


@settings(max_examples=400, deadline=None)
@given(unit_objects())
def test_any_unit_objects_give_a_sane_scale_or_a_unit_error(objects: dict[tuple[int, int], int]) -> None:
    """For every shipped drive's settings: a scale whose profile values all fit their objects
    (1 to the type's maximum), or a UnitError that names an object; nothing else."""
    for drive in load_config(REPO / "config" / "rover.yaml").drives:
        try:
            scale, _ = scale_from_objects(drive.counts_per_rev, drive.gear_ratio, drive.rated_torque_nm, objects)
            values = [(0x6081, scale.magnitude_to_drive(drive.profile_velocity_deg_s)),
                      (0x607F, scale.magnitude_to_drive(drive.max_velocity_deg_s)),
                      (0x6083, scale.acceleration_to_drive(drive.profile_acceleration_deg_s2)),
                      (0x6085, scale.acceleration_to_drive(drive.quick_stop_decel_deg_s2))]
            for index, value in values:
                written = check_drive_value(index, value, "test", "<I")
                assert 1 <= written <= TYPE_MAX["<I"]
        except UnitError as err:
            assert f"0x{err.index:04X}" in str(err) or "units per degree" in str(err)


def absurd_eds(path: Path, objects: dict[tuple[int, int], int]) -> Path:
    od = canopen.import_od(str(GENERIC_EDS), 1)
    for (index, sub), value in objects.items():
        if index not in od and sub == 0:
            od.add_object(ODVariable(f"0x{index:04X}", index, 0))
        elif index not in od:  # a ratio: numerator and denominator
            record = ODRecord(f"0x{index:04X}", index)
            for n in (0, 1, 2):
                member = ODVariable(f"sub {n}", index, n)
                member.data_type = DataType.UNSIGNED8 if n == 0 else DataType.UNSIGNED32
                member.access_type, member.default, member.default_raw = "rw", 2, "2"
                record.add_member(member)
            od.add_object(record)
        var = od[index] if sub == 0 else od[index][sub]
        var.data_type, var.access_type = DataType.UNSIGNED32, "rw"
        var.default, var.default_raw = value, str(value)
    canopen.export_od(od, str(path), doc_type="eds")
    return path


@pytest.mark.parametrize(("objects", "named"), [
    ({(0x608F, 1): 2**32 - 1, (0x608F, 2): 1}, "0x608F"),
    ({(0x6091, 1): 2**32 - 1, (0x6091, 2): 1}, "0x6091"),
    ({(0x608F, 1): 1, (0x608F, 2): 2**32 - 1}, "0x608F"),
    ({(0x6091, 1): 1, (0x6091, 2): 2**32 - 1}, "0x6091"),
    ({(0x60A9, 0): (0x80 << 24) | 0xB4 << 16 | 0x47 << 8}, "0x60A9"),  # 10^-128 rpm
    ({(0x60A9, 0): (0x7F << 24) | 0xB4 << 16 | 0x47 << 8}, "0x60A9"),  # 10^127 rpm
])
def test_a_drive_reporting_absurd_units_is_not_booted_and_nothing_is_written(
        sim_factory: SimFactory, tmp_path: Path, objects: dict[tuple[int, int], int], named: str) -> None:
    """The simulated drive's EDS says it (its values survive the boot's NMT reset)."""
    sim, config = sim_factory(make_config(1, eds=str(absurd_eds(tmp_path / "absurd.eds", objects))))
    runner = sim.simulators["can0"]
    store = runner.drive(1).store
    before = runner.call(lambda: {i: store.get(i, 0) for i in (0x6081, 0x6083, 0x6085, 0x607F)})
    with pytest.raises(BootError, match=f"boot step 'units' refused: {named}") as raised:
        MotorDriver(with_bus_overrides(config, host=sim.host, port=sim.port)).start()
    assert "\n" not in str(raised.value) and "struct" not in str(raised.value)
    after = runner.call(lambda: {i: store.get(i, 0) for i in (0x6081, 0x6083, 0x6085, 0x607F)})
    assert after == before  # no profile, limit or quick-stop deceleration written
