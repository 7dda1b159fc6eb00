"""docs/troubleshooting.md quotes messages as users meet them; each quoted message must be one the
code can produce. A quote is split at "..." (what varies: a node id, a path, a value); every
piece between must stand whole in one string literal of the code (an f-string's or a %-format's
fixed text counts; read with ast, so a piece split across two literals in the code is not one the
code prints). Also: the page lists the messages the team's users met and asked about."""

from __future__ import annotations

import ast
import re
from functools import cache

from .conftest import REPO

PAGE = REPO / "docs" / "troubleshooting.md"
PACKAGES = ("can_config", "motor_driver", "virtual_can", "nodes", "rovercan")
QUOTE = re.compile(r'"([^"]+)"')
#: Messages users met and had to ask about (issue 41): each must be on the page.
MUST_BE_LISTED = ("EDS file not found", "cannot read the config file", "is used twice", "0x8130",
                  "this process is starved", "/cmd_vel not applied", "another master is live on the bus",
                  "cannot write incidents to", "arm the rover with the service /arm")


@cache
def literals() -> tuple[str, ...]:
    """The fixed text of every string literal in the stack's code: a plain string whole, an
    f-string each fixed part on its own."""
    out: list[str] = []
    for package in PACKAGES:
        for path in (REPO / package).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text())):
                if isinstance(node, ast.JoinedStr):
                    out += [v.value for v in node.values if isinstance(v, ast.Constant) and isinstance(v.value, str)]
                elif isinstance(node, ast.Constant) and isinstance(node.value, str):
                    out.append(node.value)
    return tuple(" ".join(s.split()) for s in out)


def quoted_messages() -> list[str]:
    """The quotes of the first column of every table row of the page."""
    quotes = []
    for line in PAGE.read_text().splitlines():
        cells = line.split(" | ")
        if line.startswith("| ") and not line.startswith("| message") and len(cells) > 1:
            quotes += QUOTE.findall(cells[0])
    return quotes


def pieces(quote: str) -> list[str]:
    return [p for p in (part.strip(" :;,()") for part in quote.split("...")) if len(p) >= 4]


def produced(piece: str) -> bool:
    return any(piece in literal for literal in literals())


def test_the_page_quotes_many_messages() -> None:
    assert len(quoted_messages()) >= 30


def test_each_quoted_message_is_one_the_code_can_produce() -> None:
    missing = [f"{quote!r}: {piece!r}" for quote in quoted_messages() for piece in pieces(quote) if not produced(piece)]
    assert not missing, "quoted on the page, but in no string of the code:\n" + "\n".join(missing)


def test_the_messages_users_asked_about_are_listed() -> None:
    page = PAGE.read_text()
    assert not [m for m in MUST_BE_LISTED if m not in page]


def test_the_check_finds_a_made_up_message() -> None:
    assert not produced("busy: enable in progress")  # the page's old wording, never printed
    assert produced("another master is live on the bus")
    assert pieces("bus ... lost (...)") == ["lost"]  # 'bus' is too short to say anything: not checked
