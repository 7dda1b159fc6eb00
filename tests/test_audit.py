"""``rovercan audit`` measures on the bus what the benchmarks measure, against the simulator
serving the shipped rover config, and names the target an overloaded bus misses."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from can_config import load_config
from can_config.bits import frame_bits
from virtual_can import SimService

from .conftest import REPO, rovercan_sim

FIGURES = ("SYNC period error p50, us", "SYNC period error p99, us", "SYNC period error max, us",
           "command -> RPDO p50, ms", "command -> RPDO p99, ms", "TPDO 0x281 lost", "TPDO 0x281 late fraction",
           "SDO round trip p99, ms", "heartbeat period error p99, ms", "bus load (measured, worst-case stuffing), %",
           "bus load (planned, rovercan plan), %", "error frames")

#: Figures a machine whose cores other processes keep busy cannot meet (scheduling delay in each).
TIMING = ("period error", "command -> RPDO", "SDO round trip", "late fraction")
def audit(config: Path, *extra: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "rovercan", "audit", "--config", str(config), "--json", *extra],
                          cwd=REPO, capture_output=True, text=True, timeout=120)


def test_audit_of_the_simulated_rover_reports_every_figure_and_meets_every_other_target(tmp_path: Path) -> None:
    """Every figure is reported; every target that is not a timing figure is met; the exit code
    and the message agree with what was missed. Whether a timing target is met depends on the
    machine (a busy runner's scheduler slices are in every timing figure): that claim lives in
    the benchmarks (benchmarks/run.py), and the audit's verdict on a missed target is tested
    below on a wire that cannot meet it. The simulator runs in a process of its own, as
    `rovercan sim` does for a user."""
    shipped = REPO / "config" / "rover.yaml"
    with rovercan_sim("--config", str(shipped)) as port:
        config = tmp_path / "rover.yaml"
        config.write_text(shipped.read_text().replace("port: 29536", f"port: {port}"))
        result = audit(config, "--seconds", "2")
    rows = json.loads(result.stdout)
    names = " | ".join(r["figure"] for r in rows)
    for figure in FIGURES:
        assert figure in names, (figure, names)
    # the bus load in percent, as `rovercan plan` gives it (not a fraction beside its percentage)
    plan = subprocess.run([sys.executable, "-m", "rovercan", "plan", "--config", str(config), "--json"], cwd=REPO,
                          capture_output=True, text=True, timeout=60, check=True)
    planned = next(r["load_pct"] for r in json.loads(plan.stdout) if r["what"] == "TOTAL" and r["bus"] == "can0")
    assert next(r["measured"] for r in rows if r["figure"].startswith("bus load (planned")) == pytest.approx(planned, abs=0.1)
    missed = [r["figure"] for r in rows if r["status"] != "ok"]
    assert all(any(t in f for t in TIMING) for f in missed), missed  # TPDO loss, load, error frames: always met
    if missed:
        assert result.returncode == 1 and "rovercan audit: targets missed:" in result.stderr, result.stderr
    else:
        assert result.returncode == 0, result.stderr


def test_audit_of_an_overloaded_wire_names_the_missed_target(tmp_path: Path) -> None:
    """250 kbit/s wire time, six drives, SYNC every 10 ms: planned at 106 % (the driver would
    refuse it; the audit measures it anyway): the planned load is missed on any machine, and each
    target missed is named. How full the wire was depends on the simulated drives getting CPU to
    send (a starved simulator left it under half full in a loaded CI run): the measured load is
    judged by the figure the audit heard, its verdict the one that figure earns."""
    # an SDO answer may wait behind the overloaded wire and a starved simulator: 5 s, not 0.5
    drives = "".join(f"  - {{name: j{i}, node_id: {i}, counts_per_rev: 4096, sdo_timeout_ms: 5000}}\n" for i in range(1, 7))

    def text(port: int) -> str:
        return ("buses:\n  - {name: can0, interface: socketcand, channel: can0, bitrate: 250000, sync_period_ms: 10,"
                f" kwargs: {{host: 127.0.0.1, port: {port}}}}}\ndrives:\n" + drives)

    config = tmp_path / "overloaded.yaml"
    config.write_text(text(1))
    with SimService.from_config(load_config(config), port=0, wire_time=True, bitrate=250_000) as sim:
        config.write_text(text(sim.port))
        result = audit(config, "--seconds", "2", "--no-motion")
    assert result.returncode == 1, result.stderr
    assert "rovercan audit: targets missed:" in result.stderr
    rows = json.loads(result.stdout)
    missed = [r["figure"] for r in rows if r["status"] == "MISSED"]
    assert "bus load (planned, rovercan plan), %" in missed
    named = result.stderr.split("rovercan audit: targets missed:")[1]
    assert all(figure in named for figure in missed), (missed, named)
    (measured,) = [r for r in rows if r["figure"] == "bus load (measured, worst-case stuffing), %"]
    # between half the SYNCs alone (the bus server's real-time timer keeps them on any machine) and
    # a full wire (wire time: no frame shorter than its worst-case stuffed bits): a figure off by a
    # factor falls outside
    syncs_only = 100 * 0.5 * frame_bits(0) / 0.010 / 250_000
    assert syncs_only < measured["measured"] <= 100.5, measured
    assert (measured["status"] == "MISSED") == (measured["measured"] > 50.0), measured
