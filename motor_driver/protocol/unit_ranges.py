"""The plausible range of every unit and scaling object a drive reports, and of every value
packed for the wire from them: nothing a drive says is trusted unbounded.

Pure functions and tables; :mod:`motor_driver.protocol.units` checks the objects before it derives a
scale, boot checks each profile value before it writes it. The ranges are in docs/safety.md.
"""

from __future__ import annotations

from can_config.errors import UnitError

#: What each is, for the notes.
UNIT_OBJECT_NAMES = {0x608F: "position encoder resolution", 0x6091: "gear ratio", 0x6092: "feed constant",
                     0x60A8: "SI unit position", 0x60A9: "SI unit velocity", 0x60AA: "SI unit acceleration",
                     0x6076: "motor rated torque"}


#: The plausible range of each unit object a drive reports (docs/safety.md): anything outside is
#: a misreading, a firmware fault or a hostile node, and the drive is not booted on it.
#: (low, high, what the value is). Ratios (0x608F, 0x6091, 0x6092) are numerator / denominator.
UNIT_RANGES: dict[int, tuple[float, float, str]] = {
    0x608F: (1.0, 2.0**26, "encoder increments per motor revolution"),
    0x6091: (1e-3, 1e4, "motor revolutions per shaft revolution"),
    0x6092: (1e-3, 1e9, "feed units per shaft revolution"),
    0x6076: (1.0, 1e7, "rated torque in mNm"),
}
#: The SI prefix of 0x60A8-0x60AA (a power of ten, CiA 303-2): at most this far from 10^0.
SI_PREFIX_MAX = 9
#: A joint's resolution, in drive units per degree, whatever it comes from.
UNITS_PER_DEG_RANGE = (1e-3, 1e8)


def check_unit_objects(objects: dict[tuple[int, int], int]) -> None:
    """Every unit object against its plausible range (:data:`UNIT_RANGES`, :data:`SI_PREFIX_MAX`);
    a :class:`UnitError` names the object, the value and the range."""
    for index, (low, high, what) in UNIT_RANGES.items():
        if index == 0x6076:
            value: float | None = objects.get((index, 0)) or None
        else:
            num, den = objects.get((index, 1)), objects.get((index, 2))
            if num is None and den is None:
                continue
            if not num or not den:
                raise UnitError(f"0x{index:04X} {UNIT_OBJECT_NAMES[index]}: {num}/{den} has a zero term; a drive"
                                " reporting it cannot be scaled. Check the drive's parameters.", index=index,
                                value=float(num or 0))
            value = num / den
        if value is not None and not low <= value <= high:
            raise UnitError(f"0x{index:04X} {UNIT_OBJECT_NAMES[index]} = {value:g} ({what}) is outside the plausible"
                            f" {low:g} to {high:g}; the drive is not booted on it. Check the drive's parameters.",
                            index=index, value=value)
    for index in (0x60A8, 0x60A9, 0x60AA):
        code = objects.get((index, 0))
        if code and abs(si_parts(code)[0]) > SI_PREFIX_MAX:
            raise UnitError(f"0x{index:04X} {UNIT_OBJECT_NAMES[index]} = 0x{code:08X}: prefix 10^{si_parts(code)[0]} is"
                            f" outside 10^-{SI_PREFIX_MAX} to 10^{SI_PREFIX_MAX}; the drive is not booted on it.",
                            index=index, value=float(code))


def check_units_per_deg(**per_deg: float) -> None:
    """The drive units per joint degree a scale derived (0: the drive did not say), each within
    :data:`UNITS_PER_DEG_RANGE`."""
    low, high = UNITS_PER_DEG_RANGE
    for what, value in per_deg.items():
        if value and not low <= value <= high:
            raise UnitError(f"the drive's {what} unit makes {value:g} units per degree, outside the plausible"
                            f" {low:g} to {high:g} (from 0x608F/0x6091/0x6092/0x60A8-0x60AA); not booted on it.",
                            index=0x60A8, value=value)


def check_drive_value(index: int, value: float, what: str, fmt: str | None) -> int:
    """A magnitude (speed, acceleration, deceleration) in drive units, before it is packed for
    0x``index``: at least 1 (never 0: a zero quick-stop deceleration does not stop) and within the
    object's type, never saturated; :class:`UnitError` says which and why."""
    high = TYPE_MAX.get(fmt or "<i", 2**31 - 1)
    number = round(value)
    if not 1 <= number <= high:
        raise UnitError(f"0x{index:04X} {what}: {value:g} in the drive's units is outside 1 to {high} (the object's"
                        " type); its unit objects or the config value are wrong. Nothing was written.", index=index,
                        value=float(value))
    return int(number)


#: The largest value of each packed integer type (struct formats of motor_driver.protocol.codec).
TYPE_MAX = {"<B": 0xFF, "<H": 0xFFFF, "<I": 0xFFFF_FFFF, "<Q": 2**64 - 1, "<b": 0x7F, "<h": 0x7FFF,
            "<i": 0x7FFF_FFFF, "<q": 2**63 - 1}


def si_parts(code: int) -> tuple[int, int, int]:
    """(prefix as a signed power of ten, numerator, denominator) of an SI unit code."""
    prefix = (code >> 24) & 0xFF
    return (prefix - 256 if prefix >= 128 else prefix), (code >> 16) & 0xFF, (code >> 8) & 0xFF
