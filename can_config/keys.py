"""Each configuration key declared once, as metadata of its dataclass field (:mod:`can_config.model`):
its YAML name, kind, default, range or choices, unit and description. Parsing, defaults, the
ms -> s conversion, ``config_to_dict`` and the reference in the docs are all derived from it.
No imports of the rest of the package (the model imports this).

Owner: none; values only.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

#: A key without a default: the YAML must give it.
REQUIRED: Any = object()


@dataclass(frozen=True)
class Field:
    """One YAML key. ``kind``: "int", "float", "opt_float", "bool", "str", "name", "namespace",
    "path", "map", "list", "list_names", "opt_int" (a byte size), "number" (int or float), "variances" (six
    numbers over 0: a covariance's diagonal)."""

    kind: str
    default: Any = REQUIRED  # as the YAML says it (ms for a time whose field holds s)
    low: float | None = None
    high: float | None = None
    choices: tuple[str, ...] | None = None
    low_open: bool = False
    yaml: str = ""  # the YAML name where it is not the field's own
    scale: float = 1.0  # YAML value = field value x scale (1000: ms in YAML, s in the dataclass)
    unit: str = ""
    help: str = ""
    nested: type | None = None  # a section of its own ("map") or a list of them ("list")


def key(kind: str, default: Any = REQUIRED, low: float | None = None, high: float | None = None, *,  # noqa: PLR0913
        choices: tuple[str, ...] | None = None, low_open: bool = False, yaml: str = "", scale: float = 1.0,
        unit: str = "", help: str = "", nested: type | None = None, required: bool = False,
        attr_default: Any = REQUIRED) -> Any:
    """A dataclass field carrying its key. ``required``: the dataclass needs the value although the
    YAML has a default the parser fills in (a drive's bus, its EDS); ``attr_default``: the
    dataclass has a default although the YAML must give the key (a field after defaulted ones)."""
    spec = Field(kind, default, low, high, choices, low_open, yaml, scale, unit, help, nested)
    meta = {"key": spec}
    if attr_default is not REQUIRED:
        return dataclasses.field(default=attr_default, metadata=meta)
    if required or default is REQUIRED:
        return dataclasses.field(metadata=meta)
    if nested is not None and kind == "map":
        return dataclasses.field(default_factory=nested, metadata=meta)
    if isinstance(default, dict):
        return dataclasses.field(default_factory=dict, metadata=meta)
    if isinstance(default, list):
        return dataclasses.field(default=(), metadata=meta)
    if default is not None and scale != 1.0:
        default = round(default / scale, 9)
    return dataclasses.field(default=default, metadata=meta)


def yaml_keys(cls: type) -> dict[str, tuple[str, Field]]:
    """A section's YAML keys in the dataclass's order: YAML name -> (field name, key)."""
    out: dict[str, tuple[str, Field]] = {}
    for f in dataclasses.fields(cls):
        spec = f.metadata.get("key")
        if spec is not None:
            out[spec.yaml or f.name] = (f.name, spec)
    return out


def table(cls: type) -> dict[str, Field]:
    """A section's YAML keys: YAML name -> key."""
    return {name: spec for name, (_, spec) in yaml_keys(cls).items()}
