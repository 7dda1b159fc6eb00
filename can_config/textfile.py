"""Reading the project's text inputs (configs, scenarios): UTF-8 only, binary and UTF-16 files
refused by name, and YAML without duplicate keys (PyYAML keeps the last one silently: a config
with ``node_id: 1`` and then ``node_id: 2`` would drive node 2).

Owner: none; pure functions of a file's bytes.
"""

from __future__ import annotations

import codecs
import re
import stat
from pathlib import Path
from typing import Any

import yaml
from yaml.constructor import ConstructorError

from can_config.errors import ConfigError

#: A config or a scenario is a few kB; a file over this is not one (and is refused before it is read).
TEXT_MAX_BYTES = 1 << 20
#: Nesting deeper than this is no config (the shipped ones nest 4 levels).
YAML_MAX_DEPTH = 32


def check_regular_file(path: Path, what: str, max_bytes: int | None) -> int:
    """The file's size, or :class:`ConfigError` when it is not a regular file (a FIFO would block
    the read for ever, a device never end), is over ``max_bytes``, or cannot be reached (a symlink
    loop, no permission)."""
    try:
        info = path.stat()
    except (OSError, RuntimeError) as err:
        why = getattr(err, "strerror", None) or str(err)
        raise ConfigError(f"{path}: cannot read the {what} ({why}); check the path, its symlinks and its"
                          " permissions.") from err
    if not stat.S_ISREG(info.st_mode):
        kind = "a directory" if stat.S_ISDIR(info.st_mode) else "a FIFO" if stat.S_ISFIFO(info.st_mode) else \
            "a device or socket"
        raise ConfigError(f"{path}: the {what} is {kind}, not a regular file; give a file.")
    if max_bytes is not None and info.st_size > max_bytes:
        raise ConfigError(f"{path}: the {what} is {info.st_size:,} bytes, over the {max_bytes:,} a {what} may have;"
                          " is it the right file?")
    return info.st_size


def read_text_file(path: Path, what: str, hint: str = "give the YAML file", max_bytes: int | None = TEXT_MAX_BYTES
                   ) -> str:
    """The file as UTF-8 text (a BOM is allowed), or :class:`ConfigError` naming the file and why:
    not a regular file, over ``max_bytes`` (None: any size), binary, UTF-16 or not UTF-8."""
    check_regular_file(path, what, max_bytes)
    try:
        with path.open("rb") as file:
            raw = file.read() if max_bytes is None else file.read(max_bytes + 1)
    except OSError as err:
        raise ConfigError(f"{path}: cannot read the {what} ({err.strerror or err}); check the path and its"
                          " permissions.") from err
    if max_bytes is not None and len(raw) > max_bytes:
        raise ConfigError(f"{path}: the {what} grew past {max_bytes:,} bytes while it was read; is it the right file?")
    if raw.startswith((b"\xff\xfe", b"\xfe\xff")):
        raise ConfigError(f"{path}: the {what} is UTF-16 text; save it as UTF-8.")
    if b"\x00" in raw:
        raise ConfigError(f"{path}: the {what} is a binary file, not text; {hint}.")
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as err:
        raise ConfigError(f"{path}: the {what} is not UTF-8 text (byte 0x{raw[err.start]:02X} at offset"
                          f" {err.start}); save it as UTF-8.") from err


#: The piece a text file is checked in by :func:`check_text_file`.
TEXT_CHECK_CHUNK_BYTES = 1 << 20


def check_text_file(path: Path, what: str, hint: str) -> None:
    """As :func:`read_text_file` judges a file (UTF-8 text, not binary, not UTF-16), read in pieces
    and kept in none: a recording of any length is checked in bounded memory."""
    check_regular_file(path, what, None)
    decoder = codecs.getincrementaldecoder("utf-8")()
    offset = 0
    try:
        with path.open("rb") as file:
            while chunk := file.read(TEXT_CHECK_CHUNK_BYTES):
                if offset == 0 and chunk.startswith((b"\xff\xfe", b"\xfe\xff")):
                    raise ConfigError(f"{path}: the {what} is UTF-16 text; save it as UTF-8.")
                if b"\x00" in chunk:
                    raise ConfigError(f"{path}: the {what} is a binary file, not text; {hint}.")
                try:
                    decoder.decode(chunk)
                except UnicodeDecodeError as err:
                    raise ConfigError(f"{path}: the {what} is not UTF-8 text (byte 0x{chunk[err.start]:02X} at"
                                      f" offset {offset + err.start}); save it as UTF-8.") from err
                offset += len(chunk)
            decoder.decode(b"", final=True)
    except UnicodeDecodeError as err:
        raise ConfigError(f"{path}: the {what} is not UTF-8 text (it ends inside a character); save it as"
                          " UTF-8.") from err
    except OSError as err:
        raise ConfigError(f"{path}: cannot read the {what} ({err.strerror or err}); check the path and its"
                          " permissions.") from err


class StrictLoader(yaml.SafeLoader):
    """SafeLoader that refuses a key given twice in one mapping, and reads every number in
    exponent notation (``2e-4``, ``1e3``, ``-5E+2``, ``1.5e3``) as a float, as YAML 1.2 does
    (PyYAML follows YAML 1.1, where those are strings). A file kind with rules of its own
    subclasses it (virtual_can's scenarios) and passes the subclass to :func:`load_yaml`."""


#: No config value needs a number longer than this (digits and signs); a longer one is refused
#: with its line before Python converts it (past 4300 digits it raised ValueError with a traceback).
NUMBER_MAX_CHARS = 40


def _number_of_a_sane_length(loader: StrictLoader, node: yaml.ScalarNode) -> Any:
    if len(str(node.value)) > NUMBER_MAX_CHARS:
        raise ConstructorError(None, None, f"a number of {len(str(node.value))} characters; no config value needs more"
                               f" than {NUMBER_MAX_CHARS}", node.start_mark)
    return (loader.construct_yaml_int if node.tag.endswith(":int") else loader.construct_yaml_float)(node)


StrictLoader.add_constructor("tag:yaml.org,2002:int", _number_of_a_sane_length)
StrictLoader.add_constructor("tag:yaml.org,2002:float", _number_of_a_sane_length)


#: YAML 1.2's floats with an exponent that YAML 1.1 lacks (no dot, or an unsigned exponent).
EXPONENT_FLOAT = re.compile(r"^[-+]?(?:[0-9][0-9_]*(?:\.[0-9_]*)?|\.[0-9_]+)[eE][-+]?[0-9]+$")
StrictLoader.add_implicit_resolver("tag:yaml.org,2002:float", EXPONENT_FLOAT, list("-+.0123456789"))


def _mapping_without_duplicates(loader: StrictLoader, node: yaml.MappingNode) -> dict[Any, Any]:
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


StrictLoader.add_constructor(yaml.resolver.BaseResolver.DEFAULT_MAPPING_TAG, _mapping_without_duplicates)


def load_yaml(path: Path, what: str, loader: type[StrictLoader] = StrictLoader) -> Any:
    """A YAML file's data, or :class:`ConfigError` naming the file, the line and the problem."""
    text = read_text_file(path, what)
    try:
        data = yaml.load(text, Loader=loader)
    except RecursionError as err:
        raise ConfigError(f"{path}: the {what} nests deeper than YAML can be read here (over"
                          f" {YAML_MAX_DEPTH} levels are never a {what}).") from err
    except yaml.YAMLError as err:
        mark = getattr(err, "problem_mark", None)
        where = f" line {mark.line + 1}, column {mark.column + 1}:" if mark is not None else ""
        problem = getattr(err, "problem", None) or str(err)
        raise ConfigError(f"{path}:{where} not valid YAML: {problem}.") from err
    if (depth := nesting(data)) > YAML_MAX_DEPTH:
        raise ConfigError(f"{path}: the {what} nests {depth} levels deep, over the {YAML_MAX_DEPTH} a {what} may;"
                          " is it the right file?")
    return data


def nesting(data: Any) -> int:
    """How deep lists and mappings nest in ``data`` (a scalar: 0), without recursion; each list or
    mapping counted once (YAML aliases share them, and may even make one contain itself)."""
    deepest, stack, seen = 0, [(data, 1)], set()
    while stack:
        item, depth = stack.pop()
        if id(item) in seen:
            continue
        if isinstance(item, (dict, list)):
            seen.add(id(item))
        if isinstance(item, dict):
            children = [*item.keys(), *item.values()]
        elif isinstance(item, list):
            children = item
        else:
            continue
        deepest = max(deepest, depth)
        stack.extend((child, depth + 1) for child in children)
    return deepest
