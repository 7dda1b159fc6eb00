"""argparse types of the CLI: every number is checked where it is read, so a bad one is refused
with its argument's name and the allowed range (exit 2) before any bus is opened."""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable


def whole(low: int, high: int) -> Callable[[str], int]:
    """A whole number in low..high (decimal or 0x hex)."""
    def parse(text: str) -> int:
        try:
            value = int(text, 0)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number ({low}..{high})") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{value} is out of range {low}..{high}")
        return value
    parse.bounds = (low, high, False)  # type: ignore[attr-defined]  # read by the tests
    return parse


def real(low: float, high: float, *, nonzero: bool = False) -> Callable[[str], float]:
    """A finite number in low..high (never NaN or infinite); ``nonzero``: 0 is refused too."""
    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a number ({low:g}..{high:g})") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"{text!r} is not a finite number; give one in {low:g}..{high:g}")
        if not low <= value <= high or (nonzero and value == 0):
            raise argparse.ArgumentTypeError(f"{value:g} is out of range {low:g}..{high:g}"
                                             + (", and not 0" if nonzero else ""))
        return value
    parse.bounds = (low, high, nonzero)  # type: ignore[attr-defined]  # read by the tests
    return parse
