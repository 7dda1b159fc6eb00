"""The mutation score of ``./dev mutants`` from mutmut's results: killed, survived, not run,
per file, and every survivor's name (docs/testing.md gives each one's reason or its test)."""

from __future__ import annotations

import subprocess
import sys
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def main() -> int:
    out = subprocess.run([str(ROOT / ".venv" / "bin" / "mutmut"), "results", "--all", "true"], cwd=ROOT,
                         capture_output=True, text=True, check=False).stdout
    counts: Counter[tuple[str, str]] = Counter()
    survivors = []
    for line in out.splitlines():
        name, _, status = line.strip().rpartition(": ")
        if not name:
            continue
        module = name.split(".x")[0]
        counts[(module, status)] += 1
        if status == "survived":
            survivors.append(name)
    for module in sorted({m for m, _ in counts}):
        killed, survived = counts[(module, "killed")], counts[(module, "survived")]
        other = sum(n for (m, s), n in counts.items() if m == module and s not in ("killed", "survived"))
        tried = killed + survived
        score = f"{100 * killed / tried:.1f} %" if tried else "-"
        print(f"{module}: {killed} killed, {survived} survived, {other} not run or timed out; score {score}")
    for name in survivors:
        print(f"survived: {name}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
