"""The command channel's rule, forced interleaving by interleaving: a stop's frame is the last a
drive gets of everything decided before it; nothing but a later operation's enable follows it.

The channel takes its senders as callbacks (as the set-point handshake does), so these tests
record every frame it sends, in order, with no bus: they are exact and fast, and they are
what ``./dev mutants`` runs against the channel. Each competitor runs on a thread of its own;
the channel's hooks say where a thread is ("...: decided" inside the critical section,
"...: waiting for the lock" before it blocks), so no test depends on timing.
"""

from __future__ import annotations

import dataclasses
import threading
from collections.abc import Callable

import pytest

from can_config import load_drive_od
from can_config.config import GENERIC_EDS
from can_config.errors import CommandRejected, DriveStateError
from can_config.objects import OperationMode
from motor_driver.drive.command.busy import Op
from motor_driver.drive.command.channel import CommandChannel
from motor_driver.protocol.cia402 import Command
from motor_driver.protocol.pdo import plan_pdos

RPDO1, RPDO2, RPDO3, RPDO4 = 0x201, 0x301, 0x401, 0x501
QUICK_STOP, ENABLE = int(Command.QUICK_STOP), int(Command.ENABLE_OPERATION)
JOIN_S = 10.0  # a hang, not a timing claim


class Wire:
    """Every frame the channel sends, in order: (cob-id, controlword, the rest)."""

    def __init__(self) -> None:
        self.frames: list[tuple[int, int, bytes]] = []
        self.sdo_words: list[int] = []
        self.wakes = 0

    def send(self, cob: int, data: bytes) -> None:
        self.frames.append((cob, int.from_bytes(data[:2], "little"), bytes(data[2:])))

    def words(self) -> list[int]:
        return [cw for _, cw, _ in self.frames]


def make_channel(wire: Wire) -> CommandChannel:
    plan = plan_pdos(load_drive_od(str(GENERIC_EDS), 1), 1)
    return CommandChannel("joint1", 1, plan, wire.send, wire.sdo_words.append, lambda: setattr(wire, "wakes",
                                                                                                wire.wakes + 1))


def commanding(channel: CommandChannel) -> CommandChannel:
    """The channel as after an enable marked done and a live velocity command."""
    enabled(channel)
    with channel.command("velocity command") as frames:
        frames.velocity(10, live=True)
    channel.mark_enabled(Op(0, "enable", channel.generation), lambda: None)
    return channel


def enabled(channel: CommandChannel) -> None:
    """The channel as after an enable: this driver's last word Enable Operation."""
    with channel.operation("enable") as op:
        channel.transition(op, "enable", Command.ENABLE_OPERATION)


class Hooks:
    """Runs ``action`` on its own thread when a thread reaches ``point``, and waits for it to
    finish or to block on the channel's lock (its "waiting for the lock" point)."""

    def __init__(self, channel: CommandChannel) -> None:
        self._actions: dict[str, Callable[[], None]] = {}
        self._blocked = threading.Event()
        self.errors: list[BaseException] = []
        self.threads: list[threading.Thread] = []
        channel.set_hook(self)

    def at(self, point: str, action: Callable[[], None]) -> None:
        self._actions[point] = action

    def __call__(self, point: str) -> None:
        if point.endswith("waiting for the lock") and threading.current_thread() in self.threads:
            self._blocked.set()
        action = self._actions.pop(point, None)
        if action is None:
            return
        done = threading.Event()

        def run() -> None:
            try:
                action()
            except BaseException as err:
                self.errors.append(err)
            finally:
                done.set()
                self._blocked.set()

        thread = threading.Thread(target=run, daemon=True)
        self.threads.append(thread)
        self._blocked.clear()
        thread.start()
        assert self._blocked.wait(JOIN_S), f"the action at {point!r} neither finished nor blocked"

    def join(self) -> None:
        for thread in self.threads:
            thread.join(JOIN_S)
            assert not thread.is_alive()


@pytest.fixture
def wire() -> Wire:
    return Wire()


def test_a_stop_inside_a_transitions_critical_section_waits_and_its_frame_comes_last(wire: Wire) -> None:
    channel = make_channel(wire)
    hooks = Hooks(channel)
    hooks.at("enable: decided", lambda: channel.stop(Command.QUICK_STOP, "quick stop"))
    with channel.operation("enable") as op:
        channel.transition(op, "enable", Command.ENABLE_OPERATION)
    hooks.join()
    assert wire.words() == [ENABLE, QUICK_STOP]  # decided before the stop, so sent before it


def test_a_stop_decided_while_a_transition_waits_for_the_lock_ends_that_transition(wire: Wire) -> None:
    """The stop gets the lock first: the transition's check, under the lock, sees it."""
    channel = make_channel(wire)
    holding = threading.Event()
    release = threading.Event()

    def hold() -> None:  # as a frame of another thread's would (the receive thread's reply)
        with channel._lock:
            holding.set()
            release.wait(JOIN_S)

    def stop_first() -> None:  # on the transition's thread, before it blocks on the lock
        stopper = threading.Thread(target=lambda: channel.stop(Command.QUICK_STOP, "quick stop"), daemon=True)
        stopper.start()
        release.set()  # the stop is the only one waiting: it gets the lock
        stopper.join(JOIN_S)
        assert not stopper.is_alive()

    with channel.operation("enable") as op:
        holder = threading.Thread(target=hold, daemon=True)
        holder.start()
        assert holding.wait(JOIN_S)
        channel.set_hook(lambda point: stop_first() if point == "enable: waiting for the lock" else None)
        with pytest.raises(DriveStateError, match="interrupted by quick stop"):
            channel.transition(op, "enable", Command.ENABLE_OPERATION)
    holder.join(JOIN_S)
    assert wire.words() == [QUICK_STOP]


def test_no_transition_of_an_operation_begun_before_a_stop_leaves(wire: Wire) -> None:
    channel = make_channel(wire)
    with channel.operation("enable") as op:
        channel.stop(Command.QUICK_STOP, "quick stop")
        with pytest.raises(DriveStateError, match="interrupted by quick stop"):
            channel.transition(op, "enable", Command.SWITCH_ON)
    assert wire.words() == [QUICK_STOP]
    with channel.operation("enable") as later:  # a later, explicit enable is obeyed
        channel.transition(later, "enable", Command.ENABLE_OPERATION)
    assert wire.words() == [QUICK_STOP, ENABLE]


def test_a_nested_operation_runs_under_its_callers_generation(wire: Wire) -> None:
    """Homing's enable: a stop during homing ends the nested enable before any frame of it."""
    channel = make_channel(wire)
    with channel.operation("home") as home:
        channel.stop(Command.QUICK_STOP, "quick stop")
        with pytest.raises(DriveStateError, match="interrupted by quick stop"), channel.operation("enable", home):
            pass
        with pytest.raises(DriveStateError, match="interrupted by quick stop"):
            channel.transition(home, "enable", Command.SHUTDOWN)
    assert wire.words() == [QUICK_STOP]


def test_an_operation_removes_only_its_own_busy_mark(wire: Wire) -> None:
    channel = make_channel(wire)
    hooks = Hooks(channel)
    with channel.operation("enable") as op:
        assert channel.busy == "enable"
        with pytest.raises(CommandRejected, match="busy with enable"), channel.operation("home"):
            pass
        assert channel.busy == "enable"  # the refused one took nothing away
        with channel.stopping(Command.QUICK_STOP, "quick stop"):
            assert channel.busy == "enable"  # still registered, by its own token
        assert channel.busy == "enable"
        with pytest.raises(DriveStateError, match="interrupted by quick stop"):
            channel.check(op, "enable")
    del hooks
    assert channel.busy is None  # nothing stale: every later command may run
    enabled(channel)
    with channel.command("velocity") as frames:
        frames.velocity(100, live=True)


def test_a_stopped_channel_sends_no_motion_frame(wire: Wire) -> None:
    channel = make_channel(wire)
    enabled(channel)
    channel.stop(Command.QUICK_STOP, "quick stop")
    for send in (lambda f: f.velocity(10, live=True), lambda f: f.torque(10, live=True), lambda f: f.setpoint(10),
                 lambda f: f.stream_position(OperationMode.CYCLIC_SYNC_POSITION, 10, False)):
        with pytest.raises(CommandRejected, match="a stop came first"), channel.command("motion") as frames:
            send(frames)
    with channel.command("brake") as frames:
        assert not frames.brake(velocity_mode=True)  # a brake carries Enable Operation: not after a stop
    assert wire.words() == [ENABLE, QUICK_STOP]
    assert not channel.velocity_commanded and not channel.was_enabled


def test_the_supervisor_never_waits_and_never_brakes_after_a_stop(wire: Wire) -> None:
    channel = make_channel(wire)
    enabled(channel)
    with channel.command("velocity") as frames:
        assert channel.try_command("the watchdog") is None  # the lock is taken: it returns at once
        frames.velocity(100, live=True)
    assert channel.velocity_commanded
    with channel.operation("home"):
        assert channel.try_command("the watchdog") is None  # an operation runs
    frames = channel.try_command("the watchdog")
    assert frames is not None
    try:
        assert frames.brake(velocity_mode=True)
    finally:
        channel.release()
    assert wire.frames[-1][0] == RPDO3 and int.from_bytes(wire.frames[-1][2][:4], "little") == 0


def test_the_handshake_reply_never_follows_a_stop(wire: Wire) -> None:
    channel = make_channel(wire)
    enabled(channel)
    with channel.command("move") as frames:
        frames.setpoint(1000)
    assert wire.frames[-1][0] == RPDO2
    channel.stop(Command.QUICK_STOP, "quick stop")
    channel.on_status(True)  # the acknowledge arrives after the stop
    assert wire.words()[-1] == QUICK_STOP
    assert channel.handshake_idle


def test_the_handshake_reply_before_a_stop_comes_before_its_frame(wire: Wire) -> None:
    """The receive thread's reply takes the channel's lock: a stop decided while it is out waits."""
    channel = make_channel(wire)
    enabled(channel)
    with channel.command("move") as frames:
        frames.setpoint(1000)
    hooks = Hooks(channel)
    original = wire.send

    def send_and_stop(cob: int, data: bytes) -> None:
        if int.from_bytes(data[:2], "little") == ENABLE and cob == RPDO1 and not hooks.threads:
            hooks.at("now", lambda: channel.stop(Command.QUICK_STOP, "quick stop"))
            hooks("now")  # the stop runs now, on its own thread, while the reply goes out
        original(cob, data)

    channel._send = send_and_stop
    channel.on_status(True)  # the acknowledge: bit 4 cleared, with Enable Operation
    hooks.join()
    assert wire.words()[-2:] == [ENABLE, QUICK_STOP]


def test_a_controlword_by_sdo_is_followed_by_the_stop_decided_meanwhile() -> None:
    """No RPDO maps the controlword: a transition's SDO write comes after the lock, so a stop
    decided in between is written again after it."""
    wire = Wire()
    plan = plan_pdos(load_drive_od(str(GENERIC_EDS), 1), 1)
    no_cw = dataclasses.replace(plan, rpdos=())
    channel = CommandChannel("joint1", 1, no_cw, wire.send, wire.sdo_words.append, lambda: None)
    sdo_writes = wire.sdo_words

    def write(word: int) -> None:
        sdo_writes.append(word)
        if word == ENABLE:  # the stop lands while the enable's SDO is on its way
            channel.stop(Command.QUICK_STOP, "quick stop")

    channel._write_cw_sdo = write
    with channel.operation("enable") as op:
        channel.transition(op, "enable", Command.ENABLE_OPERATION)
    assert sdo_writes == [ENABLE, QUICK_STOP, QUICK_STOP]
    assert not wire.frames



# ---------------------------------------------------------------------------- exact frames
def rpdo(wire: Wire, cob: int) -> list[tuple[int, bytes]]:
    return [(cw, rest) for c, cw, rest in wire.frames if c == cob]


def test_motion_frames_byte_by_byte(wire: Wire) -> None:
    channel = make_channel(wire)
    enabled(channel)
    with channel.command("velocity command") as frames:
        frames.velocity(-1000, live=True, stream=True)
    assert rpdo(wire, RPDO3)[-1] == (ENABLE, (-1000).to_bytes(4, "little", signed=True))
    assert channel.velocity_commanded and channel.stream_velocity_counts_s == -1000
    assert channel.last_velocity_cmd > 0
    with channel.command("velocity command") as frames:
        frames.velocity(5, live=False)
    assert channel.stream_velocity_counts_s == -1000 and not channel.velocity_commanded  # not a stream
    with channel.command("torque command") as frames:
        frames.torque(-250, live=True)
    assert rpdo(wire, RPDO4)[-1] == (ENABLE, (-250).to_bytes(2, "little", signed=True))
    assert channel.velocity_commanded
    with channel.command("move") as frames:
        frames.setpoint(123456)
    assert rpdo(wire, RPDO2)[-1] == (ENABLE | 0x10 | 0x20, (123456).to_bytes(4, "little", signed=True))
    assert channel.target_counts == 123456


def test_halt_is_kept_on_targets_and_cleared_by_a_setpoint(wire: Wire) -> None:
    channel = make_channel(wire)
    enabled(channel)
    with channel.command("halt") as frames:
        frames.halt(True)
    assert wire.words()[-1] == ENABLE | 0x100 and channel.cw == ENABLE | 0x100
    with channel.command("velocity command") as frames:
        frames.velocity(7, live=True)
        frames.torque(7, live=True)
    assert rpdo(wire, RPDO3)[-1][0] == ENABLE | 0x100 and rpdo(wire, RPDO4)[-1][0] == ENABLE | 0x100
    with channel.command("move") as frames:
        frames.setpoint(10)  # a new target clears the halt
    assert rpdo(wire, RPDO2)[-1][0] == ENABLE | 0x30 and channel.cw == ENABLE
    with channel.command("halt") as frames:
        frames.halt(True)
        frames.halt(False)
    assert wire.words()[-1] == ENABLE and channel.cw == ENABLE


def test_streamed_positions_byte_by_byte(wire: Wire) -> None:
    channel = make_channel(wire)
    enabled(channel)
    with channel.command("set-point") as frames:
        frames.stream_position(OperationMode.CYCLIC_SYNC_POSITION, -42, False)
    assert rpdo(wire, RPDO2)[-1] == (ENABLE, (-42).to_bytes(4, "little", signed=True))
    with channel.command("set-point") as frames:
        frames.stream_position(OperationMode.CYCLIC_SYNC_POSITION, 43, True)  # its target went by SDO
    assert wire.frames[-1][:2] == (RPDO1, ENABLE) and channel.target_counts == 43
    with channel.command("set-point") as frames:
        frames.stream_position(OperationMode.INTERPOLATED_POSITION, 44, True)
    assert wire.frames[-1][:2] == (RPDO1, ENABLE | 0x10)  # enable ip mode beside it


def test_a_brake_sends_zero_and_ends_the_velocity_command(wire: Wire) -> None:
    channel = make_channel(wire)
    enabled(channel)
    for velocity_mode, cob, zero in ((True, RPDO3, bytes(4)), (False, RPDO4, bytes(2))):
        with channel.command("command") as frames:
            frames.velocity(99, live=True) if velocity_mode else frames.torque(99, live=True)
            assert frames.brake(velocity_mode=velocity_mode)
        assert rpdo(wire, cob)[-1] == (ENABLE, zero)
        assert not channel.velocity_commanded


def test_a_refusal_names_the_command(wire: Wire) -> None:
    channel = make_channel(wire)
    for send, doing in ((lambda f: f.velocity(1, live=True), "velocity command"),
                        (lambda f: f.torque(1, live=True), "torque command"), (lambda f: f.setpoint(1), "move"),
                        (lambda f: f.stream_position(OperationMode.CYCLIC_SYNC_POSITION, 1, False), "set-point")):
        with pytest.raises(CommandRejected, match=f"joint1: {doing} refused: a stop came first"), \
                channel.command(doing) as frames:
            send(frames)
    frames = channel.try_command("the watchdog")
    assert frames is not None
    try:
        with pytest.raises(CommandRejected, match="the watchdog refused"):
            frames.velocity(1, live=True)
    finally:
        channel.release()
    with channel.operation("enable") as op:
        channel.stop(Command.QUICK_STOP, "quick stop")
        with pytest.raises(DriveStateError, match="joint1 \\(node 1\\): enable interrupted by quick stop"):
            channel.mark_enabled(op, lambda: None)
    assert not channel.was_enabled


def test_enabled_by_us_is_this_drivers_last_word_or_a_recent_enable(wire: Wire) -> None:
    channel = make_channel(wire)
    assert not channel.enabled_by_us(0.0, 1.0)
    enabled(channel)
    sent = channel.last_enable_sent
    assert channel.enabled_by_us(sent + 100.0, 1.0)  # the last word is Enable Operation
    channel.stop(Command.QUICK_STOP, "quick stop")
    assert channel.enabled_by_us(sent + 0.5, 1.0)  # a stop followed it, but it was sent just now
    assert not channel.enabled_by_us(sent + 1.0, 1.0) and not channel.enabled_by_us(sent + 2.0, 1.0)


def test_forgetting_ends_what_was_commanded(wire: Wire) -> None:
    channel = commanding(make_channel(wire))
    assert channel.was_enabled and channel.velocity_commanded
    channel.forget_commanded()
    assert not channel.was_enabled and not channel.velocity_commanded
    assert wire.words()[-1] == ENABLE  # forgetting sends nothing


@pytest.mark.parametrize("stop", [Command.QUICK_STOP, Command.SHUTDOWN, Command.DISABLE_VOLTAGE])
def test_a_stop_ends_what_was_commanded(wire: Wire, stop: Command) -> None:
    """After a stop no velocity command is live (the watchdog has nothing to end) and the drive
    is not taken for enabled by this driver (recover() does not re-enable it)."""
    channel = commanding(make_channel(wire))
    assert channel.was_enabled is True and channel.velocity_commanded is True
    channel.stop(stop, "a stop")
    assert channel.was_enabled is False and channel.velocity_commanded is False
    assert wire.words()[-1] == int(stop)


def test_no_stop_is_written_again_after_a_transition_by_sdo_that_no_stop_followed() -> None:
    wire = Wire()
    plan = plan_pdos(load_drive_od(str(GENERIC_EDS), 1), 1)
    channel = CommandChannel("joint1", 1, dataclasses.replace(plan, rpdos=()), wire.send, wire.sdo_words.append,
                             lambda: None)
    with channel.operation("enable") as op:
        channel.transition(op, "enable", Command.SHUTDOWN)
    assert wire.sdo_words == [int(Command.SHUTDOWN)]  # a stop word, but no stop came: written once
    channel.stop(Command.QUICK_STOP, "quick stop")
    with channel.operation("enable") as later:
        channel.transition(later, "enable", Command.ENABLE_OPERATION)
    assert wire.sdo_words == [int(Command.SHUTDOWN), QUICK_STOP, ENABLE]  # the stop came before it began


def test_a_new_channel_has_commanded_nothing(wire: Wire) -> None:
    """Before anything: not enabled by this driver (so recover() does not enable a drive it never
    enabled), no velocity live, no target, no stop yet, not closed, no frame sent."""
    channel = make_channel(wire)
    assert (channel.cw, channel.target_counts, channel.stream_velocity_counts_s, channel.generation) == (0, 0, 0, 0)
    assert channel.was_enabled is False and channel.velocity_commanded is False and channel.closed is False
    assert channel.last_velocity_cmd == 0.0 and channel.last_enable_sent == 0.0
    assert channel.busy is None and wire.frames == []
    with channel.operation("enable") as op:  # the first operation is not taken for preempted
        channel.check(op, "enable")


def test_only_an_enable_word_is_stamped_as_sent(wire: Wire) -> None:
    channel = make_channel(wire)
    with channel.operation("enable") as op:
        channel.transition(op, "enable", Command.SHUTDOWN)
        channel.transition(op, "enable", Command.SWITCH_ON)
        assert channel.last_enable_sent == 0.0
        channel.transition(op, "enable", Command.ENABLE_OPERATION)
    assert channel.last_enable_sent > 0.0


def test_reset_forget_and_close(wire: Wire) -> None:
    channel = commanding(make_channel(wire))
    channel.reset(123)  # a boot: nothing commanded, the target where the shaft is
    assert (channel.cw, channel.target_counts) == (0, 123)
    assert channel.was_enabled is False and channel.velocity_commanded is False
    channel.forget(456)
    assert channel.target_counts == 456
    channel.forget()
    assert channel.target_counts == 456  # no position given: the target stays
    sent = len(wire.frames)
    channel.close()
    assert channel.closed is True and wire.wakes >= 1
    with pytest.raises(DriveStateError, match="shut down"), channel.operation("enable") as op:
        channel.check(op, "enable")
    assert len(wire.frames) == sent  # none of this sent a frame


def test_operation_enabled_during_this_drivers_own_enable_is_its_own_however_late(wire: Wire) -> None:
    """Judged by order: while an enable of this driver's is under way, a drive's Operation Enabled
    is its doing, even long after the Enable Operation frame (a starved process reads it late);
    with no enable under way and another word since, it is not (another master's)."""
    channel = make_channel(wire)
    with channel.operation("enable") as op:
        channel.transition(op, "enable", Command.ENABLE_OPERATION)
        channel.transition(op, "enable", Command.SHUTDOWN)  # its last word no longer Enable Operation
        late = channel.last_enable_sent + 60.0  # a minute later by the receive thread's clock
        assert channel.enabled_by_us(late, within_s=1.0)
    assert not channel.enabled_by_us(late, within_s=1.0)
