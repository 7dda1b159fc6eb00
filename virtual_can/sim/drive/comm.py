"""The simulated drive's CANopen communication: NMT, SDO server, PDO engine (configured from
the object dictionary, re-configurable by SDO with the CiA 301 procedure enforced),
heartbeat consumer and node guarding, frames in. Runner thread only.

The heartbeat consumer and life guarding keep the bus time of what they heard (the frame's stamp,
the time it reached the bus) and are judged against the bus time the runner gives a tick: a frame
handled late is still in time if it reached the bus in time (a real drive's controller stamps its
receive FIFO; a simulator starved of the CPU must not take its own lateness for a silent host).
Without a bus time (a frame with no stamp, a tick given none) the handling time stands for it.
"""

from __future__ import annotations

import logging
import struct

import can
from canopen.objectdictionary import ObjectDictionary

from can_config.objects import OD, PDO_COB_ID_INVALID, STRUCT_FORMAT, FunctionCode, NmtCommand, NmtState
from virtual_can.sim.drive.model import (
    BUS_CLOCK_STEP_S,
    BUS_OFFSET_SLEW,
    CYCLIC_GAP_S,
    EMCY_PDO_LENGTH,
    SAVE_RANGES,
    SAVE_SIGNATURE,
    SAVE_SILENCE_S,
    MotorParams,
    Pdo,
)
from virtual_can.sim.drive.plant import Plant
from virtual_can.sim.objects import ABORT_DEVICE_STATE, ABORT_NO_OBJECT, ABORT_NOT_MAPPABLE, ABORT_PDO_LENGTH, SdoAbort

logger = logging.getLogger(__name__)


class CommNode(Plant):
    """Layer 4: NMT, SDO, PDO, heartbeat consumer, node guarding."""

    def __init__(self, node_id: int, od: ObjectDictionary, params: MotorParams | None = None,
                 *, name: str | None = None) -> None:
        super().__init__(node_id, od, params, name=name)
        self.store.on_write = self._on_sdo_write
        self._report_encoder()
        self._units_from_od()
        self._reset_node(now=0.0, announce=False)

    def _reset_node(self, now: float, announce: bool = True) -> list[can.Message]:
        self.store.reset(0x0000, 0xFFFF)
        self._reset_motion()
        return self._reset_comm(now, announce)

    def _reset_motion(self) -> None:
        """A reset: the state machine and set-points start again; the shaft stays where it is."""
        self._init_motion()
        self._pending_rpdos = []
        self._cycle_rpdos = []
        self._delayed_sdo = None

    def _reset_comm(self, now: float, announce: bool) -> list[can.Message]:
        self.store.reset(0x1000, 0x1FFF)
        self.nmt = NmtState.PRE_OPERATIONAL
        self._held.clear()  # its transmit queue does not outlive the reset
        self._consumer_seen = {}  # 0x1016 sub -> bus time its producer was last heard
        self._guard_toggle = 0  # node guarding: the toggle bit of the next answer (0 after a reset)
        self._guarded_at = None  # the bus time of the last guard; life guarding armed by the first one
        self._load_consumers()
        self._rebuild_pdos()
        self._next_heartbeat = now
        if not announce:
            return []
        return [self._msg(FunctionCode.HEARTBEAT + self.node_id, b"\x00")]

    def _rebuild_pdos(self) -> None:
        self.rpdos = {}
        self.tpdos = []
        for comm, mapping in self._pdo_entries(OD.RPDO_COMM, OD.RPDO_MAP):
            pdo = self._pdo(comm, mapping)
            if pdo is not None:
                self.rpdos[pdo.cob_id] = pdo
        for comm, mapping in self._pdo_entries(OD.TPDO_COMM, OD.TPDO_MAP):
            pdo = self._pdo(comm, mapping)
            if pdo is not None:
                pdo.inhibit_s = int(self.store.get(comm, 3, 0)) * 100e-6  # type: ignore[arg-type]
                pdo.event_s = int(self.store.get(comm, 5, 0)) / 1000.0  # type: ignore[arg-type]
                self.tpdos.append(pdo)

    def _pdo_entries(self, comm_base: int, map_base: int) -> list[tuple[int, int]]:
        """(communication, mapping) index of each PDO the object dictionary has, in order."""
        out = []
        for n in range(512):
            if not self.store.has(comm_base + n, 1):
                break
            out.append((comm_base + n, map_base + n))
        return out

    def _pdo(self, comm: int, mapping: int) -> Pdo | None:
        cob = int(self.store.get(comm, 1, PDO_COB_ID_INVALID))  # type: ignore[arg-type]
        if cob & PDO_COB_ID_INVALID:
            return None
        entries = []
        count = int(self.store.get(mapping, 0, 0))  # type: ignore[arg-type]
        for sub in range(1, count + 1):
            raw = int(self.store.get(mapping, sub, 0))  # type: ignore[arg-type]
            index, subindex = raw >> 16, (raw >> 8) & 0xFF
            var = self.store.vars.get((index, subindex))
            fmt = STRUCT_FORMAT.get(var.data_type) if var is not None else None
            if var is None or fmt is None:
                logger.warning("node %d: PDO 0x%04X maps 0x%04X:%d, which it cannot carry;"
                               " PDO disabled", self.node_id, mapping, index, subindex)
                return None
            entries.append((index, subindex, fmt))
        return Pdo(cob & 0x1FFFFFFF, int(self.store.get(comm, 2, 255)), entries)  # type: ignore[arg-type]

    def _check_mapping_write(self, index: int, subindex: int) -> None:
        """CiA 301 procedure: a mapping changes only while the PDO is invalid and sub 0 is 0."""
        comm = index - 0x200
        cob = int(self.store.get(comm, 1, 0))  # type: ignore[arg-type]
        if not cob & PDO_COB_ID_INVALID:
            raise SdoAbort(ABORT_DEVICE_STATE, index, subindex,
                           "set bit 31 of the PDO COB-ID before changing its mapping")
        if subindex == 0:
            count = int(self.store.get(index, 0))  # type: ignore[arg-type]
            bits = 0
            for sub in range(1, count + 1):
                raw = int(self.store.get(index, sub, 0))  # type: ignore[arg-type]
                var = self.store.vars.get((raw >> 16, (raw >> 8) & 0xFF))
                if var is None:
                    raise SdoAbort(ABORT_NO_OBJECT, index, subindex,
                                   f"mapped object 0x{raw >> 16:04X} does not exist")
                if not var.mappable:
                    raise SdoAbort(ABORT_NOT_MAPPABLE, index, subindex,
                                   f"0x{var.index:04X} cannot be PDO-mapped")
                bits += raw & 0xFF
            if bits > 64:
                raise SdoAbort(ABORT_PDO_LENGTH, index, subindex, f"{bits} bits > 64")
        elif int(self.store.get(index, 0)) != 0:  # type: ignore[arg-type]
            raise SdoAbort(ABORT_DEVICE_STATE, index, subindex,
                           "set sub-index 0 to 0 before changing mapping entries")

    def _store_parameters(self, subindex: int) -> None:
        """0x1010:sub = "save" (CiA 301): keep the values that a reset or power cycle restores."""
        if int(self.store.get(OD.STORE_PARAMETERS, subindex, 0)) != SAVE_SIGNATURE:  # type: ignore[arg-type]
            return
        low, high = SAVE_RANGES.get(subindex, (0x1000, 0x9FFF))
        kept = self.store.save(low, high)
        self.store.set(OD.STORE_PARAMETERS, subindex, 1)  # reads back its capability: saves on command
        logger.info("node %d: %d parameters saved (0x1010:%d)", self.node_id, kept, subindex)

    def _on_sdo_write(self, index: int, subindex: int) -> None:
        self._count_write_for_reset(index, subindex)
        if 0x1600 <= index <= 0x17FF or 0x1A00 <= index <= 0x1BFF:
            self._check_mapping_write(index, subindex)
            self._rebuild_pdos()
        elif 0x1400 <= index <= 0x15FF or 0x1800 <= index <= 0x19FF:
            self._rebuild_pdos()
        elif index == OD.CONTROLWORD:
            self._apply_controlword()
        elif index == OD.MODES_OF_OPERATION:
            self._set_mode()
        elif index in (OD.TARGET_POSITION, OD.INTERPOLATION_DATA):
            self._csp_target()
        elif index == OD.CONSUMER_HEARTBEAT_TIME:
            self._consumer_seen.pop(subindex, None)  # a new entry is armed by its next heartbeat
            self._load_consumers()
        elif index == OD.STORE_PARAMETERS:
            self._store_parameters(subindex)

    def _load_consumers(self) -> None:
        """The active 0x1016 entries: sub -> (watched node id, consumer time in s)."""
        self._consumers = {}
        for (index, sub), value in self.store.values.items():
            if index == OD.CONSUMER_HEARTBEAT_TIME and sub > 0 and isinstance(value, int):
                node, time_ms = (value >> 16) & 0x7F, value & 0xFFFF
                if node and time_ms:
                    self._consumers[sub] = (node, time_ms / 1000.0)

    def _on_heartbeat(self, node: int, stamp: float) -> None:
        if self.faults.heartbeat_deaf:
            return
        for sub, (watched, _) in self._consumers.items():
            if watched == node:
                self._consumer_seen[sub] = stamp

    def _check_consumers(self, now: float, bus_now: float) -> list[can.Message]:
        """Each armed consumer whose producer was not heard for its consumer time, on the bus's
        time line (``bus_now``: every frame that reached the bus by then was heard)."""
        out: list[can.Message] = []
        for sub, (node, timeout_s) in self._consumers.items():
            seen = self._consumer_seen.get(sub)
            if seen is not None and bus_now - seen > timeout_s:
                del self._consumer_seen[sub]  # disarmed until that producer is heard again
                logger.warning("node %d: heartbeat of node %d lost (consumer time %.0f ms)", self.node_id,
                               node, timeout_s * 1000)
                out += self._connection_lost(now)
                self._communication_error()
        return out

    def _communication_error(self) -> None:
        """CiA 301 0x1029:1, the device's behaviour on a communication error (a heartbeat consumer
        timeout), where its dictionary has it: 0 to PRE-OPERATIONAL if OPERATIONAL (its PDOs stop;
        the default of most drives that list it), 1 no change, 2 to STOPPED."""
        behaviour = self.store.get(OD.ERROR_BEHAVIOUR, 1, 1)  # absent: no change
        if behaviour == 0 and self.nmt == NmtState.OPERATIONAL:
            self.nmt = NmtState.PRE_OPERATIONAL
        elif behaviour == 2:
            self.nmt = NmtState.STOPPED

    def _on_guard(self, stamp: float) -> list[can.Message]:
        """CiA 301 node guarding, the slave's side: answer toggle bit + NMT state; the first
        guard arms life guarding (``stamp``: the guard's bus time)."""
        answer = self._guard_toggle << 7 | int(self.nmt)
        if not self.faults.guard_toggle_stuck:
            self._guard_toggle ^= 1
        self._guarded_at = stamp
        return [self._msg(FunctionCode.HEARTBEAT + self.node_id, bytes([answer]))]

    def _check_life_guard(self, now: float, bus_now: float) -> list[can.Message]:
        """Life guarding: no guard for guard time x life time factor (0x100C x 0x100D, both set)
        on the bus's time line is a lost master: EMCY 0x8130 and the 0x6007 reaction, as for a
        heartbeat consumer."""
        guard_ms = int(self.store.get(OD.GUARD_TIME, 0, 0))  # type: ignore[arg-type]
        factor = int(self.store.get(OD.LIFE_TIME_FACTOR, 0, 0))  # type: ignore[arg-type]
        if (self._guarded_at is None or not guard_ms or not factor
                or bus_now - self._guarded_at <= guard_ms * factor / 1000):
            return []
        self._guarded_at = None  # disarmed until the next guard
        logger.warning("node %d: life guarding event (no guard for %d ms x %d)", self.node_id, guard_ms, factor)
        out = self._connection_lost(now)
        self._communication_error()
        return out

    def on_frame(self, msg: can.Message, now: float, stamp: float | None = None) -> list[can.Message]:
        """A frame handled at ``now`` (the runner's monotonic time) that reached the bus at
        ``stamp`` (the bus's time line; default: its own stamp, else ``now``); the frames that
        leave now (any behind a held one are held too: :meth:`release`)."""
        return self._in_order(self._answer(msg, now, stamp))

    def _in_order(self, frames: list[can.Message]) -> list[can.Message]:
        """``frames`` to leave now, unless frames of this drive are held: then behind them (one
        transmit queue: a drive's frames leave in the order it made them)."""
        if self._held and frames:
            return self._hold(frames, self._held[-1][0])
        return frames

    def _hold(self, frames: list[can.Message], due: float) -> list[can.Message]:
        """Hold ``frames`` until ``due`` (the runner's clock), never ahead of one held before."""
        due = max(due, self._held[-1][0]) if self._held else due
        self._held.extend((due, frame) for frame in frames)
        return []

    @property
    def next_release(self) -> float | None:
        """When the oldest held frame is due (the runner's clock); None when none is held."""
        return self._held[0][0] if self._held else None

    def release(self, now: float) -> list[can.Message]:
        """The held frames due by ``now``, in order (an unplugged drive's are lost)."""
        out = []
        while self._held and self._held[0][0] <= now:
            out.append(self._held.popleft()[1])
        return [] if self.faults.unplugged else out

    def _answer(self, msg: can.Message, now: float, stamp: float | None) -> list[can.Message]:
        if self.faults.unplugged or now < self.faults.power_off_until or msg.is_extended_id:
            return []  # CANopen (CiA 301) uses 11-bit identifiers only
        stamp = stamp if stamp is not None else msg.timestamp or now
        if msg.is_remote_frame:  # the one remote frame CANopen uses: the master's node guard
            return self._on_guard(stamp) if msg.arbitration_id == FunctionCode.HEARTBEAT + self.node_id else []
        cob = msg.arbitration_id
        data = bytes(msg.data)
        if cob == 0:
            return self._on_nmt(data, now)
        if 0x701 <= cob <= 0x77F and cob != FunctionCode.HEARTBEAT + self.node_id and data:
            self._on_heartbeat(cob - 0x700, stamp)
            return []
        if cob == (int(self.store.get(OD.COB_ID_SYNC, 0, 0x80)) & 0x7FF):  # type: ignore[arg-type]
            return self._on_sync(now, stamp)
        if self.nmt == NmtState.STOPPED:
            return []
        if cob == FunctionCode.SDO_RX + self.node_id:
            saving = len(data) >= 4 and data[0] & 0xE0 == 0x20 and data[1:3] == OD.STORE_PARAMETERS.to_bytes(2, "little")
            if self.faults.sdo_delay_s > 0 or saving:  # a save keeps the drive's SDO server silent a while
                self._delayed_sdo = (now + max(self.faults.sdo_delay_s, SAVE_SILENCE_S if saving else 0.0), data)
                return []
            return self._sdo(data)
        pdo = self.rpdos.get(cob)
        if pdo is not None and self.nmt == NmtState.OPERATIONAL:
            self.counters["rpdo"] += 1
            if 0 <= pdo.trans_type <= 240:
                self._pending_rpdos.append((pdo, data))
            elif self.faults.cw_per_cycle:  # the drive reads its objects at its next cycle
                self._cycle_rpdos.append((pdo, data))
            else:  # taken at once, and the statusword answers at once (a drive's next cycle)
                self._apply_rpdo(pdo, data)
                self._now = now
                self._update_status()
                return [] if self.faults.unplugged else self._event_tpdos(now)
        return []

    def _sdo(self, data: bytes) -> list[can.Message]:
        self.counters["sdo"] += 1
        resp = self.sdo.handle(data)
        out = [self._msg(FunctionCode.SDO_TX + self.node_id, resp)] if resp is not None else []
        if self.faults.reset_pending:  # fault injection: it resets after (or instead of) answering
            self.faults.reset_pending = False
            logger.warning("node %d: resets itself at an SDO write (fault injection)", self.node_id)
            return (out if self.faults.reset_answers else []) + self._reset_node(self._now, self.faults.reset_bootup)
        return out

    def _count_write_for_reset(self, index: int, subindex: int) -> None:
        """Fault injection: is this SDO write the one the drive resets at (Faults.reset_at_*)?"""
        faults = self.faults
        at = faults.reset_at_object
        if at is not None and at[0] == index and at[1] in (None, subindex):
            faults.reset_at_object = None
            faults.reset_pending = True
        if faults.reset_at_writes:
            faults.reset_at_writes[0] -= 1
            if faults.reset_at_writes[0] <= 0:
                faults.reset_at_writes.pop(0)
                faults.reset_pending = True

    def _on_nmt(self, data: bytes, now: float) -> list[can.Message]:
        if len(data) != 2 or data[1] not in (0, self.node_id):
            return []
        cmd = data[0]
        if cmd == NmtCommand.START:
            self.nmt = NmtState.OPERATIONAL
        elif cmd == NmtCommand.STOP:
            was, self.nmt = self.nmt, NmtState.STOPPED
            if was == NmtState.OPERATIONAL:  # CiA 402 0x6007: entering NMT stopped aborts the connection
                self._connection_lost(now)  # its warning EMCY cannot go out in STOPPED
        elif cmd == NmtCommand.ENTER_PREOPERATIONAL:
            self.nmt = NmtState.PRE_OPERATIONAL
        elif cmd == NmtCommand.RESET_NODE:
            return self._reset_node(now)
        elif cmd == NmtCommand.RESET_COMMUNICATION:
            return self._reset_comm(now, announce=True)
        return []

    def _apply_rpdo(self, pdo: Pdo, data: bytes) -> None:
        self._act_on(self._write_rpdo(pdo, data))

    def _write_rpdo(self, pdo: Pdo, data: bytes) -> set[int]:
        """The RPDO's values into the object dictionary; returns the objects written."""
        need = sum(struct.calcsize(fmt) for _, _, fmt in pdo.entries)
        if len(data) < need:
            self.faults.pending.append(EMCY_PDO_LENGTH)
            return set()
        offset = 0
        for index, sub, fmt in pdo.entries:
            (value,) = struct.unpack_from(fmt, data, offset)
            offset += struct.calcsize(fmt)
            self.store.values[(index, sub)] = value
        return {index for index, _, _ in pdo.entries}

    def _act_on(self, written: set[int]) -> None:
        """What the drive does with newly written objects (once per frame, or once per cycle)."""
        if OD.MODES_OF_OPERATION in written:
            self._set_mode()
        if OD.CONTROLWORD in written:
            self._apply_controlword()
        elif written & {OD.TARGET_POSITION, OD.INTERPOLATION_DATA}:
            self._csp_target()

    def _event_tpdos(self, now: float) -> list[can.Message]:
        """Event-driven TPDOs (254/255) whose data changed, or whose event timer is due."""
        out: list[can.Message] = []
        for pdo in self.tpdos:
            if pdo.trans_type >= 254:
                due = pdo.event_s and now - pdo.last_sent >= pdo.event_s
                if now - pdo.last_sent >= pdo.inhibit_s:
                    data = pdo.pack(self.store)
                    if due or data != pdo.last_data:
                        out += self._send_pdo(pdo, data, now)
        return out

    def _sync_moment(self, now: float, stamp: float, interval: float) -> float:
        """The moment a SYNC stamped ``stamp`` (bus time) and handled at ``now`` was on the bus, on
        the runner's clock: its stamp plus the least handling delay seen (the two clocks' offset;
        a SYNC handled late, by a runner held meanwhile, was still on the bus when its stamp says)."""
        seen = now - stamp
        offset = self._bus_offset
        if offset is None or abs(seen - offset) > BUS_CLOCK_STEP_S:
            offset = seen
        else:
            offset = min(offset + BUS_OFFSET_SLEW * max(0.0, min(interval, 1.0)), seen)
        self._bus_offset = offset
        return stamp + offset

    def _on_sync(self, now: float, stamp: float) -> list[can.Message]:
        """A SYNC, at bus time ``stamp``: the cycle is measured by the bus's clock, not by when this
        process got to it (a late process takes several SYNCs at once). The synchronous TPDOs carry
        the position at the SYNC's moment (:meth:`_latch_position`), as a drive latches it."""
        interval = stamp - self._last_sync
        self._last_sync = stamp
        self._syncs += 1
        if 0.0005 < interval < CYCLIC_GAP_S:  # the cycle the cyclic modes interpolate over
            self._sync_period_s += 0.2 * (interval - self._sync_period_s)
        if self.nmt != NmtState.OPERATIONAL:
            return []
        for pdo, data in self._pending_rpdos:
            self._apply_rpdo(pdo, data)
        self._pending_rpdos.clear()
        moment = self._sync_moment(now, stamp, interval)
        self._latch_position(moment)
        out: list[can.Message] = []
        for pdo in self.tpdos:
            tt = pdo.trans_type
            if tt == 0:
                data = pdo.pack(self.store)
                if data != pdo.last_data:
                    out += self._send_pdo(pdo, data, now)
            elif 1 <= tt <= 240:
                pdo.sync_count += 1
                if pdo.sync_count >= tt:
                    pdo.sync_count = 0
                    out += self._send_pdo(pdo, pdo.pack(self.store), now)
        faults = self.faults
        if faults.latched_fault:  # a fault in this cycle, after the latch: its frames pass the latched ones
            code, faults.latched_fault = faults.latched_fault, 0
            out += self._raise_fault(code, now)
            self._update_status()
            out += self._event_tpdos(now)
            out.sort(key=lambda frame: frame.arbitration_id)
        if out and (faults.sync_delay_s or faults.sync_jitter_s):  # packed now, at the SYNC; sent late
            return self._hold(out, moment + faults.sync_delay_s + self._rng.uniform(0.0, faults.sync_jitter_s))
        return out

    def _send_pdo(self, pdo: Pdo, data: bytes, now: float) -> list[can.Message]:
        if self.faults.tpdo_silent or pdo.cob_id in self.faults.lost_tpdos:
            return []
        pdo.last_data = data
        pdo.last_sent = now
        self.counters["tpdo"] += 1
        return [self._msg(pdo.cob_id, data)]
