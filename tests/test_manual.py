"""The manual holds together: the README is a front page (under 200 lines) whose links and the
manual's all resolve, and the README's five-minute tour runs as written against `rovercan sim`
(its shell commands, with the simulator's port in $B): an example cannot rot."""

from __future__ import annotations

import json
import re
import shlex
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

from .conftest import REPO, rovercan_sim

README = REPO / "README.md"
PAGES = [README, *sorted((REPO / "docs").glob("*.md"))]
LINK = re.compile(r"\]\(([^)#\s]+)(#[^)]*)?\)")


def test_the_readme_is_a_front_page() -> None:
    assert len(README.read_text().splitlines()) < 200


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_link_resolves(page: object) -> None:
    text = page.read_text()  # type: ignore[attr-defined]
    for target, _ in LINK.findall(text):
        if target.startswith(("http://", "https://")):
            continue
        assert (page.parent / target).exists(), f"{page.name}: link to {target} leads nowhere"  # type: ignore[attr-defined]


def tour_commands() -> list[str]:
    """The tour's bench and check commands (the simulator itself, the endless monitor and the
    long-running launch are the test's to run, not the tour's)."""
    text = README.read_text()
    tour = text[text.index("## A five-minute tour"):text.index("## Safe by default")]
    lines = [ln.split("  #")[0].strip() for block in re.findall(r"```bash\n(.*?)```", tour, re.DOTALL)
             for ln in block.splitlines()]
    return [ln for ln in lines if ln.startswith("rovercan ") and not ln.startswith(("rovercan sim", "rovercan monitor",
                                                                                     "rovercan launch"))]


@pytest.fixture(scope="module")
def sim_port() -> Iterator[int]:
    with rovercan_sim("--drives", "2") as port:
        yield port


def test_the_tour_has_commands() -> None:
    assert len(tour_commands()) >= 6


@pytest.mark.parametrize("command", tour_commands())
def test_each_tour_command_runs(sim_port: int, command: str) -> None:
    bus = f"-i socketcand -c can0 --bus-kwargs host=127.0.0.1 port={sim_port}"
    argv = shlex.split(command.replace("$B", bus))
    run = subprocess.run([sys.executable, "-m", "rovercan", *argv[1:]], cwd=REPO, capture_output=True, text=True,
                         timeout=120)
    assert run.returncode == 0, f"{command}: {run.stderr[-2000:]}"
    assert "Traceback" not in run.stderr


def session_commands() -> list[tuple[str, str]]:
    """(command, the first line the manual shows after it) of each `$ rovercan ... $B` of the
    bench page's session, and of every page."""
    out = []
    for page in PAGES:
        lines = page.read_text().splitlines()
        for i, line in enumerate(lines):
            if line.startswith("$ rovercan ") and "$B" in line and "|" not in line:
                out.append((line[2:], lines[i + 1] if i + 1 < len(lines) else ""))
    return out


def test_the_bench_page_shows_a_session() -> None:
    assert len(session_commands()) >= 4


@pytest.mark.parametrize(("command", "shown"), session_commands())
def test_each_session_command_answers_as_the_manual_shows(sim_port: int, tmp_path: Path, command: str,
                                                          shown: str) -> None:
    bus = f"-i socketcand -c can0 --bus-kwargs host=127.0.0.1 port={sim_port}"
    argv = shlex.split(command.replace("$B", bus))
    run = subprocess.run([sys.executable, "-m", "rovercan", *argv[1:]], cwd=tmp_path, capture_output=True,
                         text=True, timeout=120)
    assert "Traceback" not in run.stderr
    if shown.startswith("rovercan: "):  # an error the manual shows: the same words, exit 1
        assert run.returncode == 1 and shown in run.stderr, (shown, run.stderr)
    elif shown.startswith("{"):  # JSON: the same keys and, where they are not measured, values
        assert run.returncode == 0, run.stderr
        got, want = json.loads(run.stdout), json.loads(shown)
        assert set(got) == set(want) and got["state"] == want["state"]
    else:
        assert run.returncode == 0, run.stderr
