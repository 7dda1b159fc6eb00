"""The flight recorder's plot helpers (a process each): one that finished is reaped while the
driver runs (no zombie child stays), and close() ends within its budget whatever a helper is
drawing: one still drawing at the budget is terminated and reaped. The helper's command is held
by a hook (``PLOT_COMMAND``): one that ends at once, one that waits for a signal for ever."""

from __future__ import annotations

import os
import sys
import threading
import time
from pathlib import Path

import pytest

from can_config.model import RecorderConfig
from motor_driver.protocol.cia402 import State
from motor_driver.recording import flight as recorder_module
from motor_driver.recording.flight import FlightRecorder, IncidentEvent

from .conftest import in_thread, wait_for
from .drive_states import drive_state

STATE = drive_state(name="wheel", node_id=1, angle_deg=90.0, velocity_deg_s=0.0, torque_nm=0.0, statusword=0x0637,
                   state=State.OPERATION_ENABLED, mode=9, nmt="OPERATIONAL", enabled=True, fault=False, lost=False,
                   error_code=0, error_text="", stamp=100.0, heartbeat_age_s=0.01, target_reached=False,
                   data_age_s=0.01, stale=False, foreign_master="", reference=1)


def ours(pid: int) -> str:
    """The state of ``pid`` if it is a child of this process ('Z': a zombie), else ''."""
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    except OSError:
        return ""
    return fields[0] if int(fields[1]) == os.getpid() else ""


def incident(recorder: FlightRecorder, code: int) -> None:
    recorder.sample([STATE])
    recorder.write([IncidentEvent("emcy", time.time(), "can0", node=1, drive="wheel", code=code)])


def test_a_finished_plot_helper_is_reaped_while_the_driver_runs(tmp_path: Path,
                                                                 monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(recorder_module, "PLOT_COMMAND", (sys.executable, "-c", "pass"))
    recorder = FlightRecorder(RecorderConfig(dir=tmp_path, plot=True), {"wheel": ("can0", 1)}, {"can0": "can0"})
    try:
        incident(recorder, 0x2310)
        incident(recorder, 0x3210)
        pids = recorder.helper_pids()
        assert len(pids) == 2
        wait_for(lambda: not any(ours(pid) for pid in pids), 20.0, "both helpers ended and reaped",
                 lambda: str([ours(pid) for pid in pids]))
    finally:
        recorder.close()
    assert recorder.helper_pids() == []


def test_close_ends_a_plot_still_being_drawn_at_its_budget(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(recorder_module, "PLOT_COMMAND", (sys.executable, "-c", "import signal; signal.pause()"))
    monkeypatch.setattr(recorder_module, "PLOT_WAIT_S", 0.5)
    recorder = FlightRecorder(RecorderConfig(dir=tmp_path, plot=True), {"wheel": ("can0", 1)}, {"can0": "can0"})
    incident(recorder, 0x2310)
    (pid,) = recorder.helper_pids()
    assert ours(pid) not in ("", "Z")  # drawing (held)
    closing, errors = in_thread(recorder.close, name="test-close")
    closing.join(30.0)  # a hang bound: close() waits PLOT_WAIT_S, then ends the helper
    assert not closing.is_alive() and not errors
    assert ours(pid) == ""  # ended and reaped


class _Finished:
    """A helper the writer's reap looks at first: its first poll() holds that reap in the middle of
    its rebuild of the list until ``go_on``; then (and to every later look) it says it finished."""

    pid = -1

    def __init__(self) -> None:
        self.polling, self.go_on = threading.Event(), threading.Event()
        self.polls = 0

    def poll(self) -> int:
        self.polls += 1
        if self.polls == 1:
            self.polling.set()
            self.go_on.wait(30.0)
        return 0


def test_a_helper_started_while_the_writer_reaps_is_kept_and_ended(tmp_path: Path,
                                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """write() from a tool's thread (or a test's) starts a helper while the writer thread reaps:
    the reap rebuilt the list from before the append and lost that helper, which close() then
    never ended. The helpers' list is looked at under one lock."""
    monkeypatch.setattr(recorder_module, "PLOT_COMMAND", (sys.executable, "-c", "import signal; signal.pause()"))
    monkeypatch.setattr(recorder_module, "PLOT_WAIT_S", 0.5)
    recorder = FlightRecorder(RecorderConfig(dir=tmp_path, plot=False), {"wheel": ("can0", 1)}, {"can0": "can0"})
    finished = _Finished()
    recorder._helpers = [finished]  # type: ignore[list-item]
    try:
        reaping, reap_errors = in_thread(recorder._reap, name="test-reap")
        assert finished.polling.wait(30.0), "the reap looked at the finished helper"
        starting, start_errors = in_thread(lambda: recorder._plot_in_helper(tmp_path / "incident.json"),
                                           name="test-start")
        # unlocked, the start's own reap and its append run at once beside the held reap, which then
        # writes its list over theirs; locked, the start waits for the held reap. This bounded look
        # (the list read as it is, not under the lock) only gives the unlocked copy its chance.
        for _ in range(200):
            if any(p is not finished for p in list(recorder._helpers)):
                break
            time.sleep(0.01)
        finished.go_on.set()
        reaping.join(30.0)
        starting.join(30.0)
        assert not reaping.is_alive() and not starting.is_alive() and not reap_errors and not start_errors
        (pid,) = recorder.helper_pids()
        assert ours(pid) not in ("", "Z")  # kept: still drawing (held)
    finally:
        recorder.close()
    assert ours(pid) == "" and recorder.helper_pids() == []  # ended by close() and reaped
