"""Bit timing of classic CAN frames (pure, passive: used by the driver's bus-load figures, the
emulator's wire time and the bus-load planner)."""

from __future__ import annotations


def frame_bits(dlc: int, *, extended: bool = False, worst_case_stuffing: bool = True) -> int:
    """Bits one classic CAN data frame occupies on the wire, including the 3-bit intermission.

    Stuffable part: SOF to CRC (34 + 8n bits standard, 54 + 8n extended). Worst-case stuffing
    adds one bit for every four after the first. Then CRC delimiter, ACK slot and delimiter,
    EOF (7) and intermission (3): 13 bits. An 8-byte standard frame is 135 bits.
    """
    if not 0 <= dlc <= 8:
        raise ValueError(f"dlc={dlc}: classic CAN carries 0 to 8 data bytes")
    stuffable = (54 if extended else 34) + 8 * dlc
    stuff = (stuffable - 1) // 4 if worst_case_stuffing else 0
    return stuffable + stuff + 13


def frame_time_s(dlc: int, bitrate: int, *, extended: bool = False) -> float:
    """Seconds one frame takes on the wire at ``bitrate`` (worst-case stuffing)."""
    if bitrate <= 0:
        raise ValueError(f"bitrate={bitrate}: must be > 0 bit/s")
    return frame_bits(dlc, extended=extended) / bitrate
