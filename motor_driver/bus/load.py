"""Bus-load planning (pure): worst-case bits per second of every frame a config makes.

Per bus: SYNC (0 bytes) at the SYNC rate and the driver's own heartbeat. Per drive: its SYNC TPDOs every SYNC, its event
TPDO (statusword) counted once per SYNC as a worst case, one RPDO per SYNC (streamed
commands), and its heartbeat. Worst-case bit stuffing. Over 50 % of a bus is a warning, over
100 % an error: the driver refuses such a config at start-up unless forced.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass

from can_config import RoverConfig, load_drive_od
from can_config.bits import frame_bits
from can_config.objects import STRUCT_FORMAT
from motor_driver.protocol.pdo import plan_pdos

WARN_LOAD = 0.5
MAX_LOAD = 1.0


@dataclass(frozen=True)
class LoadLine:
    bus: str
    what: str
    frames_per_s: float
    bits_per_s: float


@dataclass(frozen=True)
class BusLoad:
    bus: str
    bitrate: int
    lines: tuple[LoadLine, ...]

    @property
    def bits_per_s(self) -> float:
        return sum(line.bits_per_s for line in self.lines)

    @property
    def load(self) -> float:
        return self.bits_per_s / self.bitrate


def plan_load(config: RoverConfig) -> list[BusLoad]:
    out = []
    for bus in config.buses:
        sync_hz = 1.0 / bus.sync_period_s
        beat_hz = 1.0 / bus.host_heartbeat_s
        lines = [LoadLine(bus.name, "SYNC", sync_hz, sync_hz * frame_bits(0)),
                 LoadLine(bus.name, f"host heartbeat (node {bus.host_node_id})", beat_hz, beat_hz * frame_bits(1))]
        for drive in (d for d in config.drives if d.bus == bus.name):
            plan = plan_pdos(load_drive_od(drive.eds, drive.node_id), drive.node_id)
            bits = 0.0
            frames = 0.0
            for pdo in plan.tpdos:
                size = sum(struct.calcsize(STRUCT_FORMAT[dt]) for _, _, dt in pdo.objects)
                frames += sync_hz
                bits += sync_hz * frame_bits(size)
            if plan.rpdos:
                size = max(sum(struct.calcsize(STRUCT_FORMAT[dt]) for _, _, dt in p.objects) for p in plan.rpdos)
                frames += sync_hz
                bits += sync_hz * frame_bits(size)
            hb = 1.0 / drive.heartbeat_period_s
            frames += hb
            bits += hb * frame_bits(1)
            lines.append(LoadLine(bus.name, f"{drive.name} (node {drive.node_id})", frames, bits))
        out.append(BusLoad(bus.name, bus.bitrate, tuple(lines)))
    return out
