"""The MCAP conversion benchmark (benchmarks/mcap_convert.py, issue 54) run at a tiny length, so
that it cannot rot: what it generates is the rover's SYNC traffic as the driver maps it, what it
converts with the CLI is every frame of it, and its own check of the MCAP can fail. Its figures
(time, memory) are the benchmark's, not asserted here."""

from __future__ import annotations

import json
import subprocess
import sys
from collections import Counter
from pathlib import Path

import can
import pytest
from mcap.reader import make_reader

from can_config import load_config
from can_config.eds import load_drive_od
from motor_driver.protocol.pdo import TT_SYNC, plan_pdos
from motor_driver.recording.busview import DIAGNOSTICS_TOPIC, FRAMES_TOPIC, JOINT_STATES_TOPIC, status_topic

from .conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))
from mcap_convert import problems

SCRIPT = REPO / "benchmarks" / "mcap_convert.py"
ROVER = load_config(REPO / "config" / "rover.yaml")
MINUTES = 0.05  # 3 s: 300 SYNC cycles
CYCLES = 300


def expected_ids() -> Counter[tuple[str, int]]:
    """(bus, COB-ID) of every frame of the recording: a SYNC per bus and every SYNC TPDO of the
    driver's plan per cycle, and each drive's other TPDOs once."""
    ids: Counter[tuple[str, int]] = Counter({(bus.name, 0x080): CYCLES for bus in ROVER.buses})
    for d in ROVER.drives:
        for pdo in plan_pdos(load_drive_od(d.eds, d.node_id), d.node_id).tpdos:
            ids[(d.bus, pdo.cob_id)] += CYCLES if pdo.trans_type == TT_SYNC else 1
    return ids


@pytest.mark.parametrize("fmt", ["blf", "log"])
def test_the_benchmark_converts_every_frame_it_generated(tmp_path: Path, fmt: str) -> None:
    done = subprocess.run([sys.executable, str(SCRIPT), "--minutes", str(MINUTES), "--format", fmt, "--json",
                           "--keep", str(tmp_path)], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    result = json.loads(done.stdout)
    assert result["problems"] == []
    ids = expected_ids()
    assert result["frames_generated"] == result["frames_converted"] == sum(ids.values())
    assert result["sync_cycles"] == CYCLES
    assert result["convert_peak_rss_mb"] > 0 and result["frames_per_s"] > 0 and result["mcap_mb"] > 0
    # the recording, read by python-can: the rover's frames, each on its bus
    names = {0: "can0", 1: "can1", "can0": "can0", "can1": "can1"}
    with can.LogReader(tmp_path / f"rover.{fmt}") as reader:
        assert Counter((names[m.channel], m.arbitration_id) for m in reader) == ids
    # the MCAP, read by the mcap reader: every frame, and the drives decoded
    with (tmp_path / "rover.mcap").open("rb") as f:
        topics = Counter(channel.topic for _, channel, _ in make_reader(f).iter_messages())
    assert topics == result["messages_per_channel"]
    assert topics[FRAMES_TOPIC] == sum(ids.values())
    assert topics[JOINT_STATES_TOPIC] == CYCLES
    assert all(topics[status_topic(d.name)] == CYCLES for d in ROVER.drives)
    assert topics[DIAGNOSTICS_TOPIC] >= 3


def test_its_check_finds_a_missing_channel_and_a_lost_frame() -> None:
    """The script's verdict on an MCAP that is wrong: not empty."""
    frames = sum(expected_ids().values())
    right = {FRAMES_TOPIC: frames, JOINT_STATES_TOPIC: CYCLES, DIAGNOSTICS_TOPIC: 3,
             **{status_topic(d.name): CYCLES for d in ROVER.drives}}
    assert problems(ROVER, right, right, frames, CYCLES, frames) == []
    no_joints = {k: v for k, v in right.items() if k != JOINT_STATES_TOPIC}
    assert any(JOINT_STATES_TOPIC in p for p in problems(ROVER, no_joints, no_joints, frames, CYCLES, frames))
    lost = {**right, FRAMES_TOPIC: frames - 1}
    found = problems(ROVER, lost, lost, frames, CYCLES, frames - 1)
    assert any(FRAMES_TOPIC in p for p in found) and any("generated" in p for p in found)
    assert problems(ROVER, right, lost, frames, CYCLES, frames)  # the summary disagrees with the messages
