"""The benchmarks' start of a helper process (benchmarks/stack_run.py ``started``, the simulator's
among them): its output is read while it writes, and must reach the file whole. With one file
offset shared by the child's writes and the reader's ``seek(0)``, lines landed over the start of the
file while it was read; a simulator's "simulated drive" line among them failed a quiet run now and
then ("the simulator did not start", exit status None)."""

from __future__ import annotations

import math
import sys

from .conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))
import stack_run

LINES = 30_000
CHILD = f"import time\nfor i in range({LINES}):\n    print(f'line {{i:05d}}', flush=True)\nprint('ready', flush=True)\ntime.sleep(60)"


def test_a_childs_output_read_while_it_writes_reaches_the_file_whole() -> None:
    """A child floods its output and says it is ready last; the start reads the file every 1 ms
    meanwhile (no deadline: it ends on the ready line or on the child's exit, however slow the
    machine). Every line is there once, in order, and the ready line was seen."""
    with stack_run.started("a flooding child", [sys.executable, "-c", CHILD], "ready", timeout_s=math.inf,
                           poll_s=0.001) as (_, log):
        lines = log.read_text().splitlines()
    assert lines == [f"line {i:05d}" for i in range(LINES)] + ["ready"]
