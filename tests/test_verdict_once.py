"""The verdict read once (issue 71, issue 72): a snapshot's verdict and the values published with it
come from one read of what the drive said; a drive never heard is never usable, however its
state was made; the verdict is judged again when an input changes, not per reader."""

from __future__ import annotations

import dataclasses
import itertools
import math
import time

from can_config import load_config
from can_config.eds import load_drive_od
from motor_driver.drive.ledger import DriveRecord, SupervisorPort
from motor_driver.drive.received.state import DriveCache
from motor_driver.drive.values import DriveState, Received
from motor_driver.drive.verdict import Condition
from motor_driver.protocol.cia402 import State, decode_state
from motor_driver.protocol.pdo import plan_pdos
from motor_driver.protocol.units import Scale

from .conftest import REPO
from .drive_states import drive_state

ENABLED, DISABLED = 0x0637, 0x0640  # Operation Enabled, Switch On Disabled
ARMED = ("", True, "", "", 1)  # the channel's inputs: armed (enabled by this driver), no stop


def ignore(event: object) -> None:
    """The cache's reports to a supervisor: none here."""


class SwappingCache(DriveCache):
    """A cache whose received state is another frame at each read: a newer TPDO landing between
    two reads of one snapshot (the receive thread replaces it whole at any moment)."""

    frames: tuple[Received, Received] = (Received(), Received())
    reads = 0

    @property
    def received(self) -> Received:
        self.reads += 1
        return self.frames[self.reads % 2]


def cache(kind: type[DriveCache] = DriveCache) -> DriveCache:
    config = load_config(REPO / "config" / "rover.yaml")
    d = config.drives[0]
    plan = plan_pdos(load_drive_od(d.eds, d.node_id), d.node_id)
    scale = Scale(d.counts_per_deg, d.rated_torque_nm, d.gear_ratio, invert=d.invert, offset_deg=d.offset_deg)
    record = DriveRecord()
    record.booted = True
    return kind(d, None, plan, scale, sync_period_s=0.01, record=record,  # type: ignore[arg-type]
                port=SupervisorPort(ignore, ignore))


def heard_whole(c: DriveCache, t: float) -> None:
    """Every TPDO the drive sends each SYNC heard (zeros) at ``t``: its data whole
    (``Received.whole_rx``); a TPDO sent on change after it sets the statusword."""
    for cob, layout in c._layouts.items():
        if cob in c._per_sync:
            c.on_tpdo(cob, bytearray(layout.codec.size), t)


def test_a_snapshots_verdict_and_values_come_from_one_frame() -> None:
    """Fails on a snapshot that reads the received state once for the verdict and again for the
    values (drive/state.py before issue 72): here each read is another frame."""
    c = cache(SwappingCache)
    assert isinstance(c, SwappingCache)
    now = time.monotonic()  # a fresh frame: its age well inside the bound (no duration is asserted)
    c._stale_after_s = math.inf
    c.frames = (Received(ENABLED, 8, 1000, 0, 0.0, 1.0, now, 1, whole_rx=now),
                Received(DISABLED, 8, 900_000, 0, 0.0, 2.0, now + 1e-3, 1, whole_rx=now + 1e-3))
    for _ in range(4):  # each snapshot starts on the other frame
        state = c.snapshot(ARMED)
        assert state.facts.state is state.state is decode_state(state.statusword), state
        assert state.facts.data_age_s == state.data_age_s
        expected = Condition.USABLE if state.statusword == ENABLED else Condition.STOPPED_ITSELF
        assert state.verdict.condition is expected, (state.statusword, state.verdict)
        assert (state.angle_deg == c.scale.counts_to_deg(1000)) == (state.statusword == ENABLED)
        c.reads += 1  # the next snapshot reads the other frame first
        c._judged = None


def test_a_never_heard_drive_is_not_usable_however_its_state_was_made() -> None:
    """A DriveState made by hand (a recording's, a test's, dataclasses.replace) is judged from its
    fields with an infinite staleness bound: never heard (data age inf, the default), every flag
    saying enabled, it was usable."""
    for enabled, stale, lost, fault, nmt, age in itertools.product(
            (True, False), (False, True), (False, True), (False, True), ("OPERATIONAL", "UNKNOWN"),
            (math.inf, math.nan)):
        state = drive_state(name="w", node_id=1, angle_deg=0.0, velocity_deg_s=0.0, torque_nm=0.0, statusword=ENABLED,
                           state=State.OPERATION_ENABLED, mode=8, nmt=nmt, enabled=enabled, fault=fault, lost=lost,
                           error_code=0, error_text="", stamp=0.0, heartbeat_age_s=0.0, target_reached=False,
                           stale=stale, data_age_s=age)
        assert not state.verdict.usable, state
        assert not dataclasses.replace(state, name="w2").verdict.usable
    made = drive_state(name="w", node_id=1, angle_deg=0.0, velocity_deg_s=0.0, torque_nm=0.0, statusword=ENABLED,
                      state=State.OPERATION_ENABLED, mode=8, nmt="OPERATIONAL", enabled=True, fault=False, lost=False,
                      error_code=0, error_text="", stamp=0.0, heartbeat_age_s=0.0, target_reached=False)
    assert made.verdict.condition is Condition.LATE  # every default: never heard
    assert dataclasses.replace(made, data_age_s=0.01).verdict.usable  # heard: its flags judge it


def test_a_cache_that_never_heard_its_drive_judges_it_late() -> None:
    c = cache()
    assert c.snapshot(ARMED).verdict.condition is Condition.LATE
    assert c.verdict(ARMED).condition is Condition.LATE


def test_the_verdict_is_judged_again_only_when_an_input_changes() -> None:
    """Readers between two inputs get the same value (judged once); a new input is judged anew."""
    c = cache()
    c._stale_after_s = math.inf
    heard_whole(c, 0.99)
    c.on_tpdo(0x181, bytearray(b"\x37\x06\x08"), 1.0)  # Operation Enabled, CSP
    first = c.verdict(ARMED)
    assert first.usable and c.verdict(ARMED) is first
    snapshot = c.snapshot(ARMED)
    assert snapshot.verdict.usable and c.verdict(ARMED) is snapshot.verdict  # the snapshot's judgement, shared
    c.on_tpdo(0x181, bytearray(b"\x40\x06\x08"), 1.01)  # the drive left Operation Enabled
    assert c.verdict(ARMED).condition is Condition.STOPPED_ITSELF
    assert c.verdict(("", False, "disarm", "", 1)).condition is Condition.NOT_ARMED  # the channel's input changed


def test_the_caches_snapshot_is_the_dataclass_it_stands_for() -> None:
    """The cache builds its snapshot in one step (DriveState.judged_as, not the frozen dataclass's
    __init__): every field set, equal to the dataclass made from the same values with the same
    judgement, frozen, and dataclasses.replace judges a changed copy from its fields."""
    c = cache()
    c._stale_after_s = math.inf
    heard_whole(c, 0.99)
    c.on_tpdo(0x181, bytearray(b"\x37\x06\x08"), 1.0)  # Operation Enabled, CSP
    state = c.snapshot(ARMED)
    fields = {f.name for f in dataclasses.fields(DriveState)}
    assert set(vars(state)) == fields, set(vars(state)) ^ fields
    values = {name: getattr(state, name) for name in fields - {"facts", "verdict"}}
    made = DriveState(**values, judged=(state.facts, state.verdict))  # type: ignore[arg-type]
    assert made == state and repr(made) == repr(state)
    assert made.facts is state.facts and made.verdict is state.verdict and state.verdict.usable
    try:
        state.angle_deg = 1.0  # type: ignore[misc]
    except dataclasses.FrozenInstanceError:
        pass
    else:
        raise AssertionError("the snapshot is not frozen")
    moved = dataclasses.replace(state, state=State.FAULT)
    assert moved.state is State.FAULT and not moved.verdict.usable  # judged from its own fields


def _usable_state(**changes: object) -> DriveState:
    fields: dict[str, object] = dict(
        name="w", node_id=1, angle_deg=0.0, velocity_deg_s=0.0, torque_nm=0.0, statusword=ENABLED,
        state=State.OPERATION_ENABLED, mode=8, nmt="OPERATIONAL", enabled=True, fault=False, lost=False,
        error_code=0, error_text="", stamp=0.0, heartbeat_age_s=0.01, target_reached=False, data_age_s=0.01)
    return drive_state(**(fields | changes))


def test_health_grades_a_drive_by_its_verdict_not_by_flags_of_its_own() -> None:
    """drive/health.py had its own rules for a drive: "bus lost" from the bus's flag and "heartbeat
    late" from the heartbeat's age, whatever the verdict said. A usable verdict is OK; a lost one is
    the verdict's ERROR with its cause (fails on b9f6386: ERROR "bus lost", WARN "heartbeat late")."""
    from motor_driver.diagnostics.health import ERROR, OK, drive_health

    usable = _usable_state(heartbeat_age_s=0.5)  # an old heartbeat the verdict does not count as lost
    assert usable.verdict.usable
    graded = drive_health(usable, heartbeat_period_s=0.1, bus_lost=True)
    assert graded.level == OK, graded
    assert graded.values["bus"] == "lost" and graded.values["heartbeat_age_s"] == "0.500"
    lost = _usable_state(lost=True)  # the verdict says lost: graded so, with its cause
    graded = drive_health(lost, heartbeat_period_s=0.1)
    assert graded.level == ERROR and graded.message.startswith(lost.verdict.cause), graded
