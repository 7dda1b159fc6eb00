"""Reading the project's text inputs (configs, scenarios): UTF-8 only, binary and UTF-16 files
refused by name, and YAML without duplicate keys (PyYAML keeps the last one silently: a config
with ``node_id: 1`` and then ``node_id: 2`` would drive node 2)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from yaml.constructor import ConstructorError

from can_config.errors import ConfigError


def read_text_file(path: Path, what: str, hint: str = "give the YAML file") -> str:
    """The file as UTF-8 text (a BOM is allowed), or :class:`ConfigError` naming the file and why."""
    try:
        raw = path.read_bytes()
    except OSError as err:
        raise ConfigError(f"{path}: cannot read the {what} ({err.strerror or err}); check the path and its"
                          " permissions.") from err
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise ConfigError(f"{path}: the {what} is UTF-16 text; save it as UTF-8.")
    if b"\x00" in raw:
        raise ConfigError(f"{path}: the {what} is a binary file, not text; {hint}.")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise ConfigError(f"{path}: the {what} is not UTF-8 text (byte 0x{raw[err.start]:02X} at offset"
                          f" {err.start}); save it as UTF-8.") from err


class _StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses a key given twice in one mapping."""


def _mapping_without_duplicates(loader: _StrictLoader, node: yaml.MappingNode) -> dict[Any, Any]:
    seen: dict[Any, int] = {}
    for key_node, _ in node.value:
        key = loader.construct_object(key_node, deep=True)
        try:
            first = seen.get(key)
        except TypeError:
            continue  # an unhashable key: construct_mapping reports it
        if first is not None:
            raise ConstructorError(None, None, f"duplicate key {key!r} (first given on line {first + 1}); give"
                                   " each key once", key_node.start_mark)
        seen[key] = key_node.start_mark.line
    return loader.construct_mapping(node, deep=True)


_StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _mapping_without_duplicates)


def load_yaml(path: Path, what: str) -> Any:
    """A YAML file's data, or :class:`ConfigError` naming the file, the line and the problem."""
    text = read_text_file(path, what)
    try:
        return yaml.load(text, Loader=_StrictLoader)
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" line {mark.line + 1}, column {mark.column + 1}:" if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err)
        raise ConfigError(f"{path}:{where} not valid YAML: {problem}.") from err
