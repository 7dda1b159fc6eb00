"""Bit timing of classic CAN frames (the shared passive definition in :mod:`can_config.bits`)."""

from can_config.bits import frame_bits, frame_time_s

__all__ = ["frame_bits", "frame_time_s"]
