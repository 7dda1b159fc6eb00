"""The emulator judged by an independent client: canopen's BaseNode402 in another process
boots each simulated drive, enables it and runs profile position to a target (interpolated
position on the SCHUNK PRL120, whose 0x6502 lists no profile position)."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

from can_config import GENERIC_EDS
from virtual_can import SimDriveSpec, SimService

from .conftest import REPO, SHARED_EDS

CLIENT = REPO / "tests" / "clients" / "basenode402_pp.py"
EDS_FILES = [GENERIC_EDS] + (sorted(p for p in SHARED_EDS.glob("*.eds") if p.name != "python_canopen_sample.eds")
                             if SHARED_EDS.is_dir() else [])


@pytest.mark.parametrize("eds", EDS_FILES, ids=lambda p: p.name)
def test_basenode402_reaches_operation_enabled_and_target(eds: Path) -> None:
    with SimService([SimDriveSpec(5, eds)], port=0) as sim:
        result = subprocess.run([sys.executable, str(CLIENT), sim.host, str(sim.port), "5", str(eds), "12345"],
                                capture_output=True, text=True, timeout=60)
    assert result.returncode == 0, result.stdout + result.stderr[-2000:]
    assert result.stdout.startswith("OK 1234"), result.stdout
