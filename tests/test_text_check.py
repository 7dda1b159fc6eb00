"""A recording's text is checked in pieces (can_config.textfile.check_text_file): the same
verdicts as reading it whole, wherever in the file the fault is, without holding the file."""

from __future__ import annotations

from pathlib import Path

import pytest

from can_config.errors import ConfigError
from can_config.textfile import TEXT_CHECK_CHUNK_BYTES, check_text_file

LINE = b"(1700000000.000000) can0 181#0102030405060708\n"


def test_a_fault_past_the_first_piece_is_named_with_its_offset(tmp_path: Path) -> None:
    path = tmp_path / "long.log"
    good = LINE * (TEXT_CHECK_CHUNK_BYTES // len(LINE) + 10)
    path.write_bytes(good + b"\xff" + LINE)
    with pytest.raises(ConfigError, match=rf"not UTF-8 text \(byte 0xFF at offset {len(good)}\)"):
        check_text_file(path, "recording", "give a recording")


def test_a_character_split_between_pieces_is_text(tmp_path: Path) -> None:
    path = tmp_path / "split.log"
    pad = b"x" * (TEXT_CHECK_CHUNK_BYTES - 1)
    path.write_bytes(pad + "\u00e9".encode() + b"\n")  # the two bytes of one character across the boundary
    check_text_file(path, "recording", "give a recording")


@pytest.mark.parametrize(("content", "said"), [(b"\xff\xfe(\x00", "UTF-16"), (LINE + b"\x00" + LINE, "binary file"),
                                               (LINE + b"\xc3", "ends inside a character")])
def test_binary_and_utf16_are_refused_by_name(tmp_path: Path, content: bytes, said: str) -> None:
    path = tmp_path / "bad.log"
    path.write_bytes(content)
    with pytest.raises(ConfigError, match=said):
        check_text_file(path, "recording", "give a recording")
