"""A CAN bus's health as the kernel knows it: link up or down, the controller's state
(ERROR-ACTIVE, -WARNING, -PASSIVE, BUS-OFF), its transmit and receive error counters, bitrate
and sample point, restart-ms, and the device's counters (restarts, bus-off, error-passive and
-warning entries, bus errors, lost arbitrations, dropped frames). python-can has no bus state
for SocketCAN; rtnetlink has it all (``ip -details -statistics link show can0`` reads the same).

:func:`health_from_link` is pure: it decodes one rtnetlink link message (pyroute2's
``ifinfmsg``), so it is tested here on encoded messages of every state, including the ones an
emulated controller never reaches. :func:`read_kernel_health` asks the kernel (pyroute2, a
Linux-only optional dependency). A virtual interface (vcan) has no controller: its state and
counters are ``None``, "unknown", never guessed. No thread; no state kept.
"""

from __future__ import annotations

import logging
import struct
from dataclasses import asdict, dataclass
from typing import Any

from can_config.errors import ConfigError

logger = logging.getLogger(__name__)

#: The kernel's CAN states (linux/can/netlink.h, enum can_state), as `ip -details` prints them.
STATES = {"ERROR_ACTIVE": "ERROR-ACTIVE", "ERROR_WARNING": "ERROR-WARNING", "ERROR_PASSIVE": "ERROR-PASSIVE",
          "BUS_OFF": "BUS-OFF", "STOPPED": "STOPPED", "SLEEPING": "SLEEPING"}
#: struct can_device_stats (IFLA_INFO_XSTATS of a CAN device), six u32 in this order.
XSTATS_FIELDS = ("bus_errors", "error_warning", "error_passive", "bus_off", "arbitration_lost", "restarts")
IFF_UP = 0x1
#: What each state means on a rover, and what to do.
ADVICE = {
    "ERROR-WARNING": "errors on the bus (an error counter over 96): check termination (120 ohm at both ends),"
                     " cabling and that every node uses this bitrate",
    "ERROR-PASSIVE": "many errors (an error counter over 127): this node only listens politely now; check"
                     " termination and bitrate",
    "BUS-OFF": "the controller left the bus (transmit errors over 255): nothing is sent; with restart-ms set"
               " the kernel restarts it, with restart-ms 0 it stays off until `ip link set DEV type can"
               " restart`; check termination and bitrate first",
    "STOPPED": "the controller is stopped (the interface is down)",
    "SLEEPING": "the controller sleeps",
}


@dataclass(frozen=True)
class KernelBusHealth:
    """One interface's health; ``None`` where the kernel does not know (a vcan has no controller)."""

    interface: str
    kind: str  # "can" (a controller), "vcan", or another link kind
    link_up: bool
    state: str | None = None
    tx_errors: int | None = None
    rx_errors: int | None = None
    bitrate: int | None = None
    sample_point: float | None = None  # 0.875
    restart_ms: int | None = None
    bus_errors: int | None = None
    error_warning: int | None = None
    error_passive: int | None = None
    bus_off: int | None = None
    arbitration_lost: int | None = None
    restarts: int | None = None
    rx_dropped: int | None = None
    tx_dropped: int | None = None

    @property
    def ok(self) -> bool:
        """A CAN interface, up, and ERROR-ACTIVE (or no controller to ask: vcan)."""
        return self.kind in ("can", "vcan") and self.link_up and self.state in (None, "ERROR-ACTIVE")

    def problems(self) -> list[str]:
        """What is wrong, each with what to do; empty when :attr:`ok`."""
        out = []
        if self.kind not in ("can", "vcan"):
            out.append(f"{self.interface} is not a CAN interface (link kind {self.kind}): `ip -details link show`"
                       " lists each interface's kind")
        if not self.link_up:
            out.append(f"{self.interface} is down: `rovercan can-up {self.interface}` (bitrate, restart-ms, txqueuelen"
                       " from the config)")
        if self.state is not None and self.state != "ERROR-ACTIVE" and (self.link_up or self.state != "STOPPED"):
            out.append(f"{self.interface} is {self.state}: {ADVICE.get(self.state, 'see docs/troubleshooting.md')}")
        if self.kind == "can" and self.link_up and self.restart_ms == 0:
            out.append(f"{self.interface}: restart-ms 0: after a bus-off the controller stays off until restarted by"
                       " hand; bring it up with restart-ms 100 (`rovercan can-up`)")
        return out

    def as_dict(self) -> dict[str, Any]:
        return asdict(self)


#: Counters whose rise between two reads of one interface is a problem, each with what to do.
RISING = {
    "tx_errors": "check termination and bitrate", "rx_errors": "check termination and bitrate",
    "bus_errors": "check termination and bitrate", "error_warning": "check termination and bitrate",
    "error_passive": "check termination and bitrate", "bus_off": "check termination and bitrate",
    "restarts": "the controller was restarted after a bus-off: check termination and bitrate",
    "rx_dropped": "received frames the host did not read in time (a starved process, or a receive buffer too"
                  " small)",
    "tx_dropped": "frames not sent (a full transmit queue: is any node acknowledging?)",
}


def rising(before: KernelBusHealth, after: KernelBusHealth, seconds: float) -> list[str]:
    """The counters of one interface that rose between two reads ``seconds`` apart, each said
    with what to do (empty: none rose; a counter the kernel does not have is left out). Pure."""
    out = []
    for name, advice in RISING.items():
        was, now = getattr(before, name), getattr(after, name)
        if was is not None and now is not None and now > was:
            out.append(f"{after.interface}: {name} rose by {now - was} in {seconds:.1f} s ({was} -> {now}): {advice}")
    return out


def health_from_link(msg: Any) -> KernelBusHealth:
    """Decode one rtnetlink link message (pyroute2 ``ifinfmsg``, decoded). Pure."""
    name = str(msg.get_attr("IFLA_IFNAME"))
    link_up = bool(msg["flags"] & IFF_UP) and msg.get_attr("IFLA_OPERSTATE") in ("UP", "UNKNOWN", None)
    info = msg.get_attr("IFLA_LINKINFO")
    kind = str(info.get_attr("IFLA_INFO_KIND")) if info is not None else "unknown"
    stats = msg.get_attr("IFLA_STATS64") or msg.get_attr("IFLA_STATS")
    rx_dropped = int(stats["rx_dropped"]) if stats is not None else None
    tx_dropped = int(stats["tx_dropped"]) if stats is not None else None
    if kind != "can" or info is None:
        return KernelBusHealth(name, kind, link_up, rx_dropped=rx_dropped, tx_dropped=tx_dropped)
    data = info.get_attr("IFLA_INFO_DATA")
    state = data.get_attr("IFLA_CAN_STATE") if data is not None else None
    berr = data.get_attr("IFLA_CAN_BERR_COUNTER") if data is not None else None
    timing = data.get_attr("IFLA_CAN_BITTIMING") if data is not None else None
    restart = data.get_attr("IFLA_CAN_RESTART_MS") if data is not None else None
    return KernelBusHealth(
        name, kind, link_up,
        state=STATES.get(str(state), str(state)) if state is not None else None,
        tx_errors=int(berr["txerr"]) if berr is not None else None,
        rx_errors=int(berr["rxerr"]) if berr is not None else None,
        bitrate=int(timing["bitrate"]) if timing is not None and timing["bitrate"] else None,
        sample_point=int(timing["sample_point"]) / 1000 if timing is not None and timing["sample_point"] else None,
        restart_ms=int(restart) if restart is not None else None,
        rx_dropped=rx_dropped,
        tx_dropped=tx_dropped,
        **xstats(info.get_attr("IFLA_INFO_XSTATS")),
    )


def xstats(value: object) -> dict[str, int]:
    """struct can_device_stats from IFLA_INFO_XSTATS (pyroute2 gives it as "01:00:..." hex)."""
    if not value:
        return {}
    raw = bytes.fromhex(str(value).replace(":", "")) if isinstance(value, str) else bytes(value)  # type: ignore[call-overload]
    if len(raw) < 4 * len(XSTATS_FIELDS):
        return {}
    return dict(zip(XSTATS_FIELDS, struct.unpack_from(f"<{len(XSTATS_FIELDS)}I", raw), strict=True))


def read_kernel_health(interface: str) -> KernelBusHealth:
    """Ask the kernel (rtnetlink) about ``interface``; a ConfigError naming it when it is absent
    or the kernel cannot be asked here."""
    try:
        from pyroute2 import IPRoute
    except ImportError as err:  # not Linux, or the extra is missing
        raise ConfigError(f"{interface}: reading the bus state needs pyroute2 (pip install pyroute2;"
                          " Linux only)") from err
    try:
        with IPRoute() as ipr:
            links = ipr.get_links(ifname=interface)
    except OSError as err:  # ENODEV: no such interface; a kernel without rtnetlink
        raise ConfigError(f"{interface}: no such network interface ({err.strerror or err}); `ip link show` lists"
                          " them; `rovercan can-up` brings one up") from err
    if not links:
        raise ConfigError(f"{interface}: no such network interface; `ip link show` lists them")
    return health_from_link(links[0])


__all__ = ["ADVICE", "RISING", "STATES", "KernelBusHealth", "health_from_link", "read_kernel_health", "rising",
           "xstats"]
