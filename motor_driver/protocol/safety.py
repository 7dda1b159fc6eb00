"""What keeps a drive safe when the host is gone, read back from the drive and judged (pure).

The driver writes these objects at boot (:meth:`motor_driver.drive.setup.boot.Boot.boot`); the same
rules judge what a drive reports afterwards, in the driver (after every boot, shown in
/diagnostics) and in ``rovercan safety-check`` (from the bus, by anyone):

=========================  ===================================================  ==========
check                      passes when                                          object
=========================  ===================================================  ==========
host watch                 a 0x1016 entry watches the host's node id with the   0x1016
                           configured consumer time (or the config allows a
                           drive without one: ``allowed``)
reaction to host loss      0x6007 holds the configured ``on_host_loss`` code    0x6007
                           (``n/a`` on a drive without 0x6007: its own)
quick stop                 0x605A stops the motor (1, 2, 5 or 6), not 0: coast  0x605A
software limits            0x607D equals the joint's limits in drive counts     0x607D
                           (limited joints; ``n/a`` for continuous ones)
drive heartbeat            0x1017 is the configured producer period (the host   0x1017
                           notices a dead drive)
=========================  ===================================================  ==========
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from canopen.objectdictionary import ObjectDictionary

from can_config.config import ON_HOST_LOSS, DriveConfig
from can_config.eds import has_object
from can_config.objects import OD
from motor_driver.protocol.units import Scale

PASS, FAIL, NOT_APPLICABLE, ALLOWED = "pass", "FAIL", "n/a", "allowed"
#: 0x605A codes that bring the motor to a stop (CiA 402): 0 would let it coast.
STOPPING_QUICK_STOP_CODES = frozenset({1, 2, 5, 6})


@dataclass(frozen=True)
class SafetyCheck:
    check: str
    object: str
    expected: str
    actual: str
    status: str  # PASS, FAIL, NOT_APPLICABLE or ALLOWED

    @property
    def failed(self) -> bool:
        return self.status == FAIL


#: Reads an object from the drive: its value, or None when the drive does not have it.
Reader = Callable[[int, int], "int | None"]


def watch_mode(cfg: DriveConfig, od: ObjectDictionary) -> str:
    """How a drive watches the host: ``heartbeat`` (0x1016) or ``guarding`` (0x100C/0x100D);
    ``host_watch: auto`` takes the heartbeat consumer where the drive has one. Guarding happens
    only on a bus that carries remote frames (the driver's and ``rovercan safety-check``'s rule)."""
    mode = cfg.host_watch
    if mode == "auto":
        guardable = has_object(od, OD.GUARD_TIME) and has_object(od, OD.LIFE_TIME_FACTOR)
        mode = "guarding" if guardable and not has_object(od, OD.CONSUMER_HEARTBEAT_TIME, 1) else "heartbeat"
    return mode


def guard_settings(cfg: DriveConfig) -> tuple[int, int]:
    """Node guarding (CiA 301) for a drive without a heartbeat consumer: the host guards it every
    ``heartbeat_period_ms`` (0x100C, guard time) and the drive stops itself when no guard came for
    guard time x life time factor (0x100D), at least ``host_timeout_ms``."""
    guard_ms = max(1, round(cfg.heartbeat_period_s * 1000))
    factor = max(2, math.ceil(round((cfg.host_timeout_s or 3 * cfg.heartbeat_period_s) * 1000) / guard_ms))
    return guard_ms, min(factor, 255)


def _guarding_checks(cfg: DriveConfig, read: Reader) -> list[SafetyCheck]:
    guard_ms, factor = guard_settings(cfg)
    got = (read(OD.GUARD_TIME, 0), read(OD.LIFE_TIME_FACTOR, 0))
    status = PASS if got == (guard_ms, factor) else ALLOWED if cfg.allow_no_host_watch else FAIL
    return [SafetyCheck("host watch (node guarding)", "0x100C/0x100D", f"{guard_ms} ms x {factor}",
                        f"{got[0]} ms x {got[1]}", status)]


def judge(cfg: DriveConfig, host_node_id: int, scale: Scale, read: Reader, *,
          consumer_subs: Sequence[int] = (1,), guarding: bool = False) -> list[SafetyCheck]:
    """The checks above for one drive; ``consumer_subs``: the 0x1016 sub-indexes it has;
    ``guarding``: the drive watches the host by node guarding instead (no heartbeat of its own)."""
    if guarding:
        return _guarding_checks(cfg, read) + _common_checks(cfg, scale, read, heartbeat_ms=0)
    out: list[SafetyCheck] = []
    want_ms = round((cfg.host_timeout_s or 0.0) * 1000)
    entries = [(sub, v) for sub in consumer_subs if (v := read(OD.CONSUMER_HEARTBEAT_TIME, sub)) is not None]
    watching = [f"0x1016:{sub} = node {v >> 16 & 0x7F}, {v & 0xFFFF} ms" for sub, v in entries if v & 0xFFFF]
    expected = f"node {host_node_id}, {want_ms} ms"
    good = any(v >> 16 & 0x7F == host_node_id and v & 0xFFFF == want_ms for _, v in entries)
    if good:
        status = PASS
    else:
        status = ALLOWED if cfg.allow_no_host_watch else FAIL
    out.append(SafetyCheck("host watch", "0x1016", expected,
                           "; ".join(watching) or ("no entry watches anything" if entries else "no 0x1016"), status))
    return out + _common_checks(cfg, scale, read, heartbeat_ms=round(cfg.heartbeat_period_s * 1000))


def _common_checks(cfg: DriveConfig, scale: Scale, read: Reader, *, heartbeat_ms: int) -> list[SafetyCheck]:
    """The drive's reaction, quick stop, limits and own heartbeat (0 for a guarded drive: CiA 301
    guards a node only while its heartbeat producer is off)."""
    out: list[SafetyCheck] = []
    option = read(OD.ABORT_CONNECTION_OPTION, 0)
    code = ON_HOST_LOSS[cfg.on_host_loss]
    if option is None:
        out.append(SafetyCheck("reaction to host loss", "0x6007", f"{code} ({cfg.on_host_loss})",
                               "no 0x6007: the drive's own reaction", NOT_APPLICABLE))
    else:
        out.append(SafetyCheck("reaction to host loss", "0x6007", f"{code} ({cfg.on_host_loss})", str(option),
                               PASS if option == code else FAIL))
    quick = read(OD.QUICK_STOP_OPTION, 0)
    if quick is None:
        out.append(SafetyCheck("quick stop", "0x605A", "1, 2, 5 or 6", "no 0x605A", NOT_APPLICABLE))
    else:
        out.append(SafetyCheck("quick stop", "0x605A", "1, 2, 5 or 6", str(quick),
                               PASS if quick in STOPPING_QUICK_STOP_CODES else FAIL))
    if cfg.is_continuous or cfg.min_deg is None or cfg.max_deg is None:
        out.append(SafetyCheck("software limits", "0x607D", "none (continuous joint)", "-", NOT_APPLICABLE))
    else:
        low, high = scale.limits_to_counts(cfg.min_deg, cfg.max_deg)
        got = (read(OD.SOFTWARE_POSITION_LIMIT, 1), read(OD.SOFTWARE_POSITION_LIMIT, 2))
        if None in got:
            out.append(SafetyCheck("software limits", "0x607D", f"[{low}, {high}]", "no 0x607D",
                                   NOT_APPLICABLE))
        else:
            out.append(SafetyCheck("software limits", "0x607D", f"[{low}, {high}]", f"[{got[0]}, {got[1]}]",
                                   PASS if got == (low, high) else FAIL))
    period = read(OD.PRODUCER_HEARTBEAT_TIME, 0)
    out.append(SafetyCheck("drive heartbeat", "0x1017", f"{heartbeat_ms} ms" + (" (node guarding)" if not heartbeat_ms
                                                                                  else ""),
                           "no 0x1017" if period is None else f"{period} ms",
                           PASS if period == heartbeat_ms else FAIL))
    return out


def host_heartbeat_check(host_node_id: int, period_s: float, gaps_s: Sequence[float]) -> SafetyCheck:
    """The host's own heartbeat as seen on the bus: present, at about its period."""
    expected = f"node {host_node_id} every {period_s * 1000:.0f} ms"
    if not gaps_s:
        return SafetyCheck("host heartbeat on the bus", f"0x{0x700 + host_node_id:03X}", expected,
                           "not seen: is the driver running?", FAIL)
    worst = max(gaps_s)
    status = PASS if worst <= 2 * period_s else FAIL
    return SafetyCheck("host heartbeat on the bus", f"0x{0x700 + host_node_id:03X}", expected,
                       f"{len(gaps_s) + 1} seen, longest gap {worst * 1000:.0f} ms", status)
