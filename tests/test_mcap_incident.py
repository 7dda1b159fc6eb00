"""The flight recorder's incident as MCAP and its PNG view (issue 54): the .mcap beside the BLF
read by the mcap readers (never the project's code), a lost drive drawn as missing, the CiA 402
states named on the plot."""

from __future__ import annotations

import dataclasses
import math
import subprocess
import sys
from pathlib import Path

import can

from can_config import load_config
from can_config.config import RecorderConfig
from motor_driver.drive import DriveState
from motor_driver.drive.verdict import judge
from motor_driver.protocol.cia402 import State
from motor_driver.recording.flight import FlightRecorder, IncidentEvent
from motor_driver.recording.incident import load_incident
from motor_driver.recording.plot import draw

from .conftest import REPO
from .drive_states import drive_state
from .test_mcap import ROVER, decoded, rover_frames


def test_an_incident_has_an_mcap_with_the_raw_frames_and_every_drive_decoded(tmp_path: Path) -> None:
    config = load_config(ROVER)
    frames = rover_frames(3.0)  # drive 2 of can1 (wheel_middle_right) goes silent half way
    recorder = FlightRecorder(RecorderConfig(dir=tmp_path, seconds=60.0, plot=False),
                              {d.name: (d.bus, d.node_id) for d in config.drives}, {b.name: b.channel for b in config.buses},
                              ROVER, config)
    try:
        for t, bus, cob, ext, rtr, err, dlc, data in frames:
            recorder.append(bus, can.Message(timestamp=t, arbitration_id=cob, is_extended_id=ext, is_remote_frame=rtr,
                                             is_error_frame=err, dlc=dlc, data=data))
        lost_at = frames[len(frames) // 2][0]
        written = recorder.write([IncidentEvent("heartbeat_lost", lost_at, "can1", node=2, drive="wheel_middle_right")])
    finally:
        recorder.close()
    summary = load_incident(written)
    assert summary["mcap"] == written.with_suffix(".mcap").name and summary["blf"] == written.with_suffix(".blf").name
    messages = decoded(written.with_suffix(".mcap"))
    raw = [m for topic, name, enc, m in messages if topic == "/can/frames" and name == "rovercan_msgs/msg/CanFrame"
           and enc == "ros2msg"]
    assert len(raw) == summary["frames"] == len(frames)
    first = raw[0]
    assert (first.header.frame_id, first.id, bytes(first.data)) == (frames[0][1], frames[0][2], frames[0][7])  # type: ignore[attr-defined]
    joints = [m for _, name, _, m in messages if name == "sensor_msgs/msg/JointState"]
    assert joints and all(list(m.name) == [d.name for d in config.drives] for m in joints)  # type: ignore[attr-defined]
    lost = list(joints[-1].name).index("wheel_middle_right")  # type: ignore[attr-defined]
    assert math.isnan(joints[-1].position[lost]) and not math.isnan(joints[0].position[lost])  # type: ignore[attr-defined]
    said = [s.message for _, name, _, m in messages if name == "diagnostic_msgs/msg/DiagnosticArray"
            for s in m.status]  # type: ignore[attr-defined]
    assert "incident heartbeat_lost" in said


def state(name: str, angle: float, *, lost: bool = False, s: State = State.OPERATION_ENABLED) -> DriveState:
    return drive_state(name=name, node_id=1, angle_deg=angle, velocity_deg_s=172.0, torque_nm=math.nan, statusword=0x0637,
                      state=s, mode=3, nmt="OPERATIONAL", enabled=True, fault=False, lost=lost, error_code=0,
                      error_text="", stamp=0.0, heartbeat_age_s=0.0, target_reached=False,
                      data_age_s=0.0)  # heard (never heard: no data, never usable, tests/test_verdict_once.py)


def test_a_lost_drive_is_drawn_missing_and_the_states_are_named(tmp_path: Path) -> None:
    recorder = FlightRecorder(RecorderConfig(dir=tmp_path, seconds=60.0, plot=False), {"wheel": ("can0", 1)},
                              {"can0": "can0"})
    try:
        for k in range(10):  # moving at 172 deg/s, lost from the sixth sample on
            recorder.sample([state("wheel", 10.0 * k, lost=k >= 5)])
        written = recorder.write([IncidentEvent("heartbeat_lost", 0.0, "can0", node=1, drive="wheel")])
    finally:
        recorder.close()
    row = load_incident(written)["states"]["wheel"]
    assert row["velocity_deg_s"] == [172.0] * 5 + [None] * 5 and row["angle_deg"][5:] == [None] * 5
    assert row["torque_nm"] == [None] * 10  # no torque actual value: missing, not 0
    fig = draw(load_incident(written), str(written))
    angle, velocity, _torque, states = fig.axes
    drawn = list(velocity.lines[0].get_ydata())
    assert drawn[:5] == [172.0] * 5 and all(math.isnan(v) for v in drawn[5:]), drawn
    assert all(math.isnan(v) for v in angle.lines[0].get_ydata()[5:])
    labels = {t.get_text() for t in states.get_yticklabels()}
    assert {"operation enabled", "switch on disabled", "fault"} <= labels


def test_a_drive_the_driver_judged_re_booting_is_drawn_missing_though_its_fields_look_fine(tmp_path: Path) -> None:
    """The plot reads the driver's one verdict, not flags of its own: a drive re-booting (its
    boot-up heard, being configured again) has TPDO fields that look fresh and are not news."""
    recorder = FlightRecorder(RecorderConfig(dir=tmp_path, seconds=60.0, plot=False), {"wheel": ("can0", 1)},
                              {"can0": "can0"})
    try:
        for k in range(6):
            fine = state("wheel", 10.0 * k)
            facts = fine.facts._replace(rebooting=k >= 3)
            recorder.sample([dataclasses.replace(fine, judged=(facts, judge(facts)))])
        written = recorder.write([IncidentEvent("heartbeat_lost", 0.0, "can0", node=1, drive="wheel")])
    finally:
        recorder.close()
    row = load_incident(written)["states"]["wheel"]
    assert row["angle_deg"] == [0.0, 10.0, 20.0, None, None, None]
    assert row["state"][3:] == [None] * 3


def test_the_plot_helper_says_why_there_is_no_plot(tmp_path: Path) -> None:
    recorder = FlightRecorder(RecorderConfig(dir=tmp_path, seconds=60.0, plot=True), {"wheel": ("can0", 1)},
                              {"can0": "can0"})
    try:
        written = recorder.write([IncidentEvent("emcy", 1.0, "can0", node=1, drive="wheel", code=0x2310)])
    finally:
        recorder.close()
    assert load_incident(written)["plot_skipped"] == "no drive states recorded"
    helper = subprocess.run([sys.executable, "-W", "error::RuntimeWarning", "-m", "motor_driver.recording", str(written)],
                            cwd=REPO, capture_output=True, text=True, timeout=120)
    assert helper.returncode == 1 and "no plot:" in helper.stderr and "no drive states" in helper.stderr, helper.stderr
    assert "RuntimeWarning" not in helper.stderr
