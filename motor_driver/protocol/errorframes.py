"""SocketCAN error frames (linux/can/error.h), decoded: what the controller or the kernel says
about the bus (bus-off, error passive, no ACK, ...). Pure; used by the driver's bus statistics,
``rovercan monitor`` and ``decode``."""

from __future__ import annotations

from dataclasses import dataclass

#: Error classes, the bits of an error frame's id.
CAN_ERR_TX_TIMEOUT = 0x001
CAN_ERR_LOSTARB = 0x002
CAN_ERR_CRTL = 0x004
CAN_ERR_PROT = 0x008
CAN_ERR_TRX = 0x010
CAN_ERR_ACK = 0x020
CAN_ERR_BUSOFF = 0x040
CAN_ERR_BUSERROR = 0x080
CAN_ERR_RESTARTED = 0x100
#: Controller states in data[1] of a CAN_ERR_CRTL frame.
CAN_ERR_CRTL_RX_WARNING = 0x04
CAN_ERR_CRTL_TX_WARNING = 0x08
CAN_ERR_CRTL_RX_PASSIVE = 0x10
CAN_ERR_CRTL_TX_PASSIVE = 0x20
CAN_ERR_CRTL_ACTIVE = 0x40

_CLASSES = ((CAN_ERR_BUSOFF, "bus-off"), (CAN_ERR_ACK, "no ACK (no node acknowledged: nothing else on the bus,"
                                                          " or a wiring fault)"),
            (CAN_ERR_TX_TIMEOUT, "transmit timeout"), (CAN_ERR_LOSTARB, "arbitration lost"),
            (CAN_ERR_PROT, "protocol violation"), (CAN_ERR_TRX, "transceiver error"),
            (CAN_ERR_BUSERROR, "bus error"), (CAN_ERR_RESTARTED, "controller restarted"))
_CONTROLLER = ((CAN_ERR_CRTL_TX_PASSIVE, "error passive (transmit)"), (CAN_ERR_CRTL_RX_PASSIVE, "error passive"
                                                                                               " (receive)"),
               (CAN_ERR_CRTL_TX_WARNING, "error warning (transmit)"), (CAN_ERR_CRTL_RX_WARNING, "error warning"
                                                                                                " (receive)"),
               (CAN_ERR_CRTL_ACTIVE, "back to error active"))
#: Classes after which the driver's frames do not reach the drives: the bus is lost until frames flow.
LOSING = CAN_ERR_BUSOFF | CAN_ERR_ACK


@dataclass(frozen=True)
class ErrorFrame:
    classes: int
    text: str

    @property
    def loses_the_bus(self) -> bool:
        return bool(self.classes & LOSING)


def decode_error_frame(can_id: int, data: bytes) -> ErrorFrame:
    """The error frame with id ``can_id`` (its class bits) and ``data``, in words."""
    words = [text for bit, text in _CLASSES if can_id & bit]
    if can_id & CAN_ERR_CRTL:
        state = data[1] if len(data) > 1 else 0
        words += [text for bit, text in _CONTROLLER if state & bit] or ["controller problem"]
    return ErrorFrame(can_id & 0x1FFF_FFFF, ", ".join(words) or f"error class 0x{can_id:X}")
