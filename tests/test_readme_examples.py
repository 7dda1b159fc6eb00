"""A README example is code: every Python block of the README (and of docs/, where there is
one) runs, as a user would paste it into a file, against `rovercan sim` serving the embedded
default config, and exits 0. The simulator listens on a free port; the examples find it as a user
finds a config of their own, through ``$ROVERCAN_CONFIG`` (no fixed port: another process may
hold the default one)."""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest
import yaml

from can_config import config_to_dict, load_config, with_bus_overrides
from can_config.config import CONFIG_ENV
from virtual_can import SimService

from .conftest import REPO

DOCS = [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))]
BLOCK = re.compile(r"^```python\n(.*?)^```", re.MULTILINE | re.DOTALL)


def python_blocks() -> list[tuple[str, str]]:
    out = []
    for doc in DOCS:
        for i, match in enumerate(BLOCK.finditer(doc.read_text())):
            out.append((f"{doc.name}#{i + 1}", match.group(1)))
    return out


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """The embedded default config served on a free port; yields a copy of it naming that port."""
    with SimService.from_config(load_config(), port=0) as service:
        config = with_bus_overrides(load_config(), host=service.host, port=service.port)
        path = tmp_path_factory.mktemp("readme") / "default-on-a-free-port.yaml"
        path.write_text(yaml.safe_dump(config_to_dict(config)))
        yield path


def test_the_readme_has_python_examples() -> None:
    assert len(python_blocks()) >= 2


@pytest.mark.parametrize(("where", "code"), python_blocks(), ids=[w for w, _ in python_blocks()])
def test_each_python_example_runs_against_the_simulator(sim: Path, tmp_path: Path, where: str, code: str) -> None:
    script = tmp_path / "example.py"
    script.write_text(code)
    run = subprocess.run([sys.executable, str(script)], cwd=tmp_path, capture_output=True, text=True, timeout=120,
                         env={**os.environ, CONFIG_ENV: str(sim)})
    assert run.returncode == 0, f"{where} failed:\n{code}\n{run.stderr[-3000:]}"
    assert "Traceback" not in run.stderr
