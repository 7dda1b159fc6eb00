"""argparse types of the CLI: every number is checked where it is read, so a bad one is refused
with its argument's name and the allowed range (exit 2) before any bus is opened.

Owner: none; pure checks, called by argparse on the CLI's main thread.
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
from typing import Any


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


class BusKwargs(argparse.Action):
    """``KEY=VALUE ...`` into a dict of python-can bus arguments, each value typed as python-can
    types it (``port=29536`` an int, ``tcp_tune=false`` a bool): the sim's ``--bus-kwargs``."""

    def __call__(self, parser: argparse.ArgumentParser, namespace: argparse.Namespace,
                 values: str | Sequence[Any] | None, option_string: str | None = None) -> None:
        from can.util import cast_from_string

        kwargs: dict[str, Any] = {}
        for item in values if isinstance(values, list) else [values]:
            key, sep, text = str(item).partition("=")
            if not sep or not key.isidentifier():
                raise argparse.ArgumentError(self, f"{item!r}: expected KEY=VALUE, e.g. host=127.0.0.1 port=29536")
            kwargs[key] = cast_from_string(text)
        setattr(namespace, self.dest, kwargs)
