"""The configuration manual is generated from the config's own field definitions and cannot
drift: docs/configuration.md holds exactly the generated reference, every field has a
description, and a newcomer's four-wheel config written from the manual alone (its example,
using only documented keys) parses and passes `rovercan check`."""

from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import yaml

from can_config import parse_config
from can_config.reference import BEGIN, END, SECTIONS, missing_descriptions, reference

from .conftest import REPO

MANUAL = REPO / "docs" / "configuration.md"


def test_every_field_has_a_description() -> None:
    assert missing_descriptions() == []


def test_the_manual_holds_the_generated_reference() -> None:
    text = MANUAL.read_text()
    start, end = text.index(BEGIN), text.index(END) + len(END)
    assert text[start:end] + "\n" == reference(), "docs/configuration.md is stale: python -m can_config.reference"


def documented_keys() -> dict[str, set[str]]:
    """YAML path -> the keys the manual's tables list."""
    text = MANUAL.read_text()
    out: dict[str, set[str]] = {}
    for match in re.finditer(r"^### [^\n]*\(`([^`]+)`\)\n\n(.*?)(?=\n\n)", text, re.MULTILINE | re.DOTALL):
        out[match.group(1)] = set(re.findall(r"^\| `([a-z_0-9]+)` \|", match.group(2), re.MULTILINE))
    return out


def test_the_manual_lists_every_section() -> None:
    keys = documented_keys()
    assert {path for _, path, _, _ in SECTIONS} == set(keys)
    for _, path, fields, _ in SECTIONS:
        assert keys[path] == set(fields), path


def test_a_four_wheel_config_from_the_manual_alone(tmp_path: Path) -> None:
    example = re.search(r"```yaml\n(buses:.*?)```", MANUAL.read_text(), re.DOTALL)
    assert example is not None
    data = yaml.safe_load(example.group(1))
    keys = documented_keys()
    used = {"buses[]": [k for b in data["buses"] for k in b], "drives[]": [k for d in data["drives"] for k in d],
            "drive_system": list(data["drive_system"]), "recorder": list(data["recorder"])}
    for path, names in used.items():
        assert set(names) <= keys[path], (path, set(names) - keys[path])
    config = parse_config(data)
    assert len(config.drives) == 4 and config.drive_system is not None
    assert [d.invert for d in config.drives] == [False, False, True, True]
    path = tmp_path / "rover.yaml"
    path.write_text(example.group(1))
    run = subprocess.run([sys.executable, "-m", "rovercan", "check", "--config", str(path)], cwd=REPO,
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stderr
