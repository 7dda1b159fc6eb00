"""The demo's end verdict and MotorState's ``fault`` read the drive's verdict and nothing else
(issue 71): where the verdict contradicts the flags they read before (a MotorState's ``stale``,
``enabled`` and ``fault``; a snapshot's ``fault``), the verdict wins."""

from __future__ import annotations

import math

import pytest
from hypothesis import given
from hypothesis import strategies as st

from motor_driver import DriveState, State
from motor_driver.drive.verdict import DriveFacts, Verdict, judge
from motor_driver.recording.published import motor_state_fields
from rovercan.exits import EXIT_FAILED, EXIT_OK

from .conftest import requires_ros

FRESH = {"data_age_s": 0.001, "stale_after_s": 0.1, "heartbeat_age_s": 0.01, "nmt": "OPERATIONAL", "booted": True}


def ran(first_cmd: float = 0.0, travel: float = 3.0, first_angle: float = 0.0, moved: float | None = None) -> object:
    """A demo run's track: commands from ``first_cmd`` over ``travel`` deg (0.1 deg steps, wrapped
    into [0, 360) as motor_degree sends them), the motor first measured at ``first_angle`` and then
    moving ``moved`` deg (default: to each command, 0.5 deg behind), in as many samples."""
    from rovercan.demo import Track

    track = Track()
    track.state(first_angle)
    steps = max(1, round(abs(travel) / 0.1))
    for k in range(steps + 1):
        track.command((first_cmd + travel * k / steps) % 360.0)
        if moved is None:
            track.state((first_cmd + travel * k / steps - math.copysign(0.5, travel) * (k > 0)) % 360.0)
        else:
            track.state((first_angle + moved * k / steps) % 360.0)
    return track


RAN = ran()


def verdict(**facts: object) -> Verdict:
    return judge(DriveFacts("motor", **{**FRESH, **facts}))  # type: ignore[arg-type]


def snapshot(state: State, fault: bool, facts: DriveFacts) -> DriveState:
    return DriveState(name="motor", node_id=1, angle_deg=10.0, velocity_deg_s=0.0, torque_nm=0.0, statusword=0,
                      state=state, mode=1, nmt="OPERATIONAL", error_code=0,
                      error_text="", stamp=1.0, heartbeat_age_s=0.01, target_reached=False, data_age_s=0.001, judged=(facts, judge(facts)))


def test_motor_state_fault_is_the_verdicts() -> None:
    """A FAULT statusword of a drive whose data is late is old news (the old ``fault`` flag said
    True); a lost drive (FAULT never read: the old flag's state part said False) is a fault."""
    late = DriveFacts("motor", **{**FRESH, "data_age_s": 5.0}, state=State.FAULT)  # type: ignore[arg-type]
    fields = motor_state_fields(snapshot(State.FAULT, True, late), continuous=False)
    assert not fields.fault and fields.stale and fields.state == "LATE"
    lost = DriveFacts("motor", **{**FRESH, "lost": True}, state=State.OPERATION_ENABLED)  # type: ignore[arg-type]
    fields = motor_state_fields(snapshot(State.OPERATION_ENABLED, False, lost), continuous=False)
    assert fields.fault and not fields.enabled
    faulted = DriveFacts("motor", **FRESH, state=State.FAULT)  # type: ignore[arg-type]
    assert motor_state_fields(snapshot(State.FAULT, False, faulted), continuous=False).fault


@requires_ros
def test_the_demo_fails_a_drive_whose_verdict_is_not_usable_whatever_the_message_says(
        capsys: pytest.CaptureFixture[str]) -> None:
    """The last MotorState says enabled, fresh, no fault; the drive's verdict says it stopped itself
    (its host heartbeat lost): the demo fails, naming the cause."""
    from rovercan_msgs.msg import MotorState

    from rovercan.demo import demo_verdict

    state = MotorState(angle=2.9, enabled=True, stale=False, fault=False, state="OPERATION_ENABLED")
    stopped = verdict(state=State.SWITCH_ON_DISABLED, armed=True, emcy_code=0x8130, emcy_text="heartbeat lost")
    assert demo_verdict(RAN, state, stopped) == EXIT_FAILED
    err = capsys.readouterr().err
    assert "stopped itself at the end, not usable" in err and "host heartbeat lost" in err and "CAP_SYS_NICE" in err


@requires_ros
def test_the_demo_passes_a_usable_drive_whatever_the_message_says(capsys: pytest.CaptureFixture[str]) -> None:
    from rovercan_msgs.msg import MotorState

    from rovercan.demo import demo_verdict

    state = MotorState(angle=2.9, enabled=False, stale=True, fault=True, state="LATE")
    usable = verdict(state=State.OPERATION_ENABLED, armed=True)
    assert usable.usable and demo_verdict(RAN, state, usable) == EXIT_OK
    assert capsys.readouterr().err == ""


@requires_ros
def test_the_demo_judges_no_data_that_is_not_fresh(capsys: pytest.CaptureFixture[str]) -> None:
    """Data the verdict calls late is no state (CI saw 'the drive ended in OPERATION_ENABLED, not
    Operation Enabled' from a starved process): the demo says its data were not fresh, and why."""
    from rovercan_msgs.msg import MotorState

    from rovercan.demo import demo_verdict

    state = MotorState(angle=math.nan, enabled=True, stale=False, data_age=0.4, state="OPERATION_ENABLED")
    late = verdict(state=State.OPERATION_ENABLED, armed=True, data_age_s=0.4)
    assert demo_verdict(RAN, state, late) == EXIT_FAILED
    err = capsys.readouterr().err
    assert "no fresh data from the drive at the end (motor: no data for 400 ms" in err and "not usable" not in err


def heard_nothing() -> object:
    from rovercan.demo import Track

    track = Track()
    track.state(0.0)
    return track


@requires_ros
@pytest.mark.parametrize(("track", "angle", "says"), [
    (ran(), math.nan, "carries no measured angle"),  # the last MotorState stale, the drive fresh since
    (heard_nothing(), 2.9, "no degree command was heard"),
    (ran(travel=0.0), 0.0, "too little to tell"),  # a step that rounds to none: nothing commanded, nothing seen
    (ran(travel=2.5, moved=0.5), 0.5, "did not follow"),  # within 2 deg at the end, yet the motor barely moved
    (ran(travel=-3.0, moved=0.0), 0.0, "did not follow"),
    (ran(first_cmd=350.0, travel=15.0, first_angle=350.0, moved=160.0), 150.0, "did not follow"),
])
def test_the_demo_fails_what_it_did_not_measure(track: object, angle: float, says: str,
                                                capsys: pytest.CaptureFixture[str]) -> None:
    """A NaN compares false with the tolerance and passed; a command that never moved matched a
    motor that never moved. Each now fails, saying what was not measured."""
    from rovercan_msgs.msg import MotorState

    from rovercan.demo import demo_verdict

    usable = verdict(state=State.OPERATION_ENABLED, armed=True)
    assert demo_verdict(track, MotorState(angle=angle, state="OPERATION_ENABLED"), usable) == EXIT_FAILED  # type: ignore[arg-type]
    assert says in capsys.readouterr().err


@requires_ros
def test_the_demo_passes_a_motor_that_followed_across_the_wrap() -> None:
    from rovercan_msgs.msg import MotorState

    from rovercan.demo import demo_verdict

    usable = verdict(state=State.OPERATION_ENABLED, armed=True)
    track = ran(first_cmd=355.0, travel=10.0, first_angle=354.5)  # 10 deg across 360
    assert demo_verdict(track, MotorState(angle=4.5, state="OPERATION_ENABLED"), usable) == EXIT_OK  # type: ignore[arg-type]


@requires_ros
@pytest.mark.parametrize(("travel", "first_angle"), [(180.5, 0.0), (359.5, 0.0), (360.0, 0.0), (725.0, 0.0),
                                                    (-200.0, 0.0), (20.0, 30.0)])
def test_the_demo_passes_a_long_run_and_a_motor_that_first_went_to_the_first_command(travel: float,
                                                                                       first_angle: float) -> None:
    """Travel added step by step, not the net change wrapped into +-180 (a run of 180.5 deg read as
    -179.5, one of 360 as none), and the motor's way from where it stood to the first command
    counted as commanded (a joint with an offset stands elsewhere at the start)."""
    from rovercan_msgs.msg import MotorState

    from rovercan.demo import demo_verdict

    usable = verdict(state=State.OPERATION_ENABLED, armed=True)
    track = ran(first_cmd=0.1, travel=travel, first_angle=first_angle)
    end = (0.1 + travel - math.copysign(0.5, travel)) % 360.0
    assert demo_verdict(track, MotorState(angle=end, state="OPERATION_ENABLED"), usable) == EXIT_OK  # type: ignore[arg-type]


def test_the_demo_takes_the_embedded_config_and_refuses_a_real_bus(tmp_path: object, monkeypatch: pytest.MonkeyPatch
                                                                    ) -> None:
    """$ROVERCAN_CONFIG names the rover's real buses where it is deployed (the image sets it): the
    demo, which arms its first drive, never reads it; a config given with a kernel bus is refused
    before anything opens."""
    from pathlib import Path

    from can_config import DEFAULT_CONFIG, load_config
    from can_config.errors import ConfigError
    from rovercan.demo import demo_config

    real = Path(str(tmp_path)) / "real.yaml"
    real.write_text((Path(__file__).resolve().parent.parent / "config" / "rover.yaml").read_text()
                    .replace("interface: socketcand", "interface: socketcan"))
    monkeypatch.setenv("ROVERCAN_CONFIG", str(real))
    assert demo_config(None) == load_config(DEFAULT_CONFIG)
    with pytest.raises(ConfigError, match=r"can0 \(socketcan can0\).*real bus"):
        demo_config(str(real))


@given(st.floats(-1e9, 1e9, allow_nan=False) | st.sampled_from([-1e-20, -0.0, 359.99999, 360.0, 719.999999]))
def test_a_continuous_joint_s_angle_is_in_0_to_360_as_float32_carries_it(angle: float) -> None:
    """MotorState's angle of a continuous joint lies in [0, 360) (docs): a tiny negative angle's
    remainder is 360.0 in doubles, and float32 rounds 359.99999 up to 360.0."""
    import struct

    from motor_driver.recording.published import wrapped_deg

    carried = struct.unpack("<f", struct.pack("<f", wrapped_deg(angle)))[0]
    assert 0.0 <= carried < 360.0, (angle, carried)
