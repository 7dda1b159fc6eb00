"""docs/ros.md says what /diagnostics carries and when: every node that publishes on it is in its
table "What /diagnostics carries, and when" with the statuses it names, so that a new publisher
(of event messages between the arrays, say) cannot go unsaid."""

from __future__ import annotations

import re

from .conftest import REPO

SECTION = "### What /diagnostics carries, and when"


def test_every_diagnostics_publisher_and_status_is_in_the_docs() -> None:
    text = (REPO / "docs" / "ros.md").read_text()
    assert SECTION in text
    section = text.split(SECTION, 1)[1].split("\n## ", 1)[0]
    publishers = {path.stem: path.read_text() for path in sorted((REPO / "nodes").rglob("*.py"))
                  if re.search(r"create_publisher\(\s*DiagnosticArray", path.read_text())}
    assert set(publishers) == {"driver_node", "drive_system", "follow_trajectory"}, \
        "a new /diagnostics publisher: add it to docs/ros.md"
    for module, source in publishers.items():
        names = set(re.findall(r'name=f?"(rovercan: [a-z_ ]+)', source))
        assert names, module
        missing = [n for n in names if n.strip() not in section]
        assert not missing, f"nodes/{module}.py publishes {missing} on /diagnostics; docs/ros.md's table lacks it"
    assert "event message" in section and "drive_system" in section
