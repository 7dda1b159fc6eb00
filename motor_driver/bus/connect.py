"""Opening a bus: python-can's bus from config, a socketcand server waited for with back-off
(its handshake checked), and what kind of bus it is (kernel SocketCAN or not).

No state of its own; called by the driver's constructor, the bus's worker (reconnect) and the
bench CLI.
"""

from __future__ import annotations

import logging
import socket
import threading
import time
from typing import Any

import can

from can_config.errors import BusLostError
from motor_driver.bus import library_log
from motor_driver.bus.adapters import batch_receive, bound_sends, pause_when_closed

logger = logging.getLogger(__name__)

#: Tries to open a bus whose handshake failed (a socketcand daemon's first frame can arrive with
#: its rawmode '< ok >', which python-can's client rejects); other errors are not retried.
OPEN_ATTEMPTS = 3
OPEN_RETRY_S = 0.1
#: How long the driver waits for a socketcand server to accept, and its back-off between tries.
CONNECT_TIMEOUT_S = 10.0
CONNECT_RETRY_MIN_S = 0.1
CONNECT_RETRY_MAX_S = 2.0
#: How long a socketcand server may take to greet and to finish the handshake (it takes ms).
HANDSHAKE_TIMEOUT_S = 3.0


class _QuietConnectRetries(logging.Filter):
    """python-can's socketcand client retries its connect in a loop without a pause and logs
    every failure (30,000 lines a second while a server is down): those lines are dropped;
    :func:`wait_for_server` says the same once per attempt, with back-off."""

    def filter(self, record: logging.LogRecord) -> bool:
        return not record.getMessage().startswith("Failed to connect to server")


logging.getLogger("can.interfaces.socketcand.socketcand").addFilter(_QuietConnectRetries())
library_log.install()  # canopen's abort of a transfer this driver ended on purpose: DEBUG


def _greeting(sock: socket.socket, timeout_s: float) -> str:
    """What a server says first (a socketcand server: ``< hi >``), or '' after ``timeout_s``."""
    sock.settimeout(timeout_s)
    try:
        return sock.recv(64).decode("ascii", "replace")
    except TimeoutError:
        return ""


def wait_for_server(host: str, port: int, timeout_s: float) -> None:
    """Until a socketcand server at host:port accepts and greets (``< hi >``): one attempt at a
    time, backing off from CONNECT_RETRY_MIN_S to CONNECT_RETRY_MAX_S, one log line per failed
    attempt; then :class:`BusLostError` naming host:port and the likely cause. The greeting is
    checked because python-can's handshake reads without a timeout: a port that accepts and stays
    silent (another service, a hung daemon) would hang the caller for ever."""
    deadline = time.monotonic() + timeout_s
    delay = CONNECT_RETRY_MIN_S
    attempt = 0
    while True:
        attempt += 1
        try:
            with socket.create_connection((host, port), timeout=max(0.05, min(1.0, deadline - time.monotonic()))) as sock:
                said = _greeting(sock, HANDSHAKE_TIMEOUT_S)
            if said.startswith("< hi >"):
                return
            verdict = "no socketcand server"
            why = (f"it accepted but sent {said[:40]!r}, not the socketcand greeting '< hi >'" if said else
                   f"it accepted but sent no socketcand greeting ('< hi >') within {HANDSHAKE_TIMEOUT_S:g} s")
        except OSError as err:
            verdict = "not reachable"
            why = err.strerror or str(err) or type(err).__name__
        remaining = deadline - time.monotonic()
        if remaining <= 0:
            raise BusLostError(f"socketcand server {host}:{port} {verdict} ({why}) after {attempt} attempt(s)"
                               f" in {timeout_s:g} s; is the simulator running (rovercan sim) or socketcand"
                               " started, and are host and port right?")
        # each attempt at INFO: a waiting driver says so in its log; a command gets the one line of
        # the final error (a WARNING per attempt was five lines for a refused connection)
        logger.info("socketcand server %s:%d: %s (attempt %d); next try in %.1f s", host, port, why, attempt,
                    min(delay, remaining))
        time.sleep(min(delay, remaining))
        delay = min(delay * 2, CONNECT_RETRY_MAX_S)


def _bus_within(kwargs: dict[str, Any], timeout_s: float) -> can.BusABC:
    """``can.Bus(**kwargs)`` on a helper thread, given up after ``timeout_s`` with
    :class:`BusLostError` (python-can's socketcand handshake has no timeout of its own). A bus
    that opens after it was given up is shut down by the helper."""
    outcome: list[can.BusABC | BaseException] = []
    given_up = threading.Event()
    lock = threading.Lock()  # outcome vs. given_up: the helper either hands the bus over or shuts it

    def open_it() -> None:
        try:
            result: can.BusABC | BaseException = can.Bus(**kwargs)
        except BaseException as err:  # handed to the caller's thread
            result = err
        with lock:
            if given_up.is_set():
                if isinstance(result, can.BusABC):
                    result.shutdown()
                return
            outcome.append(result)

    helper = threading.Thread(target=open_it, name="rovercan-open-bus", daemon=True)
    helper.start()
    helper.join(timeout_s)
    with lock:
        if not outcome:
            given_up.set()
            raise BusLostError(f"bus {kwargs.get('channel')} at {kwargs.get('host')}:{kwargs.get('port')}: the"
                               f" socketcand handshake did not finish within {timeout_s:g} s; the server"
                               " accepted but stopped answering (restart it)")
    result = outcome[0]
    if isinstance(result, BaseException):
        raise result
    return result


def open_bus(kwargs: dict[str, Any], connect_timeout_s: float = CONNECT_TIMEOUT_S) -> can.BusABC:
    """``can.Bus(**kwargs)``, retrying a failed protocol handshake (``can.CanError``) a few times.
    A socketcand server is first waited for (:func:`wait_for_server`), so python-can's own
    connect loop never spins, and its handshake is bounded by HANDSHAKE_TIMEOUT_S."""
    socketcand = kwargs.get("interface") == "socketcand" and "host" in kwargs and "port" in kwargs
    if socketcand:
        wait_for_server(str(kwargs["host"]), int(kwargs["port"]), connect_timeout_s)

    def opened() -> can.BusABC:
        # a lost server's end of stream pauses the receive thread instead of spinning it (adapters),
        # its frames read a batch at a time (adapters.batch_receive)
        return pause_when_closed(batch_receive(bound_sends(_bus_within(kwargs, HANDSHAKE_TIMEOUT_S)))) if socketcand \
            else can.Bus(**kwargs)

    for attempt in range(1, OPEN_ATTEMPTS):
        try:
            return opened()
        except can.CanError as err:
            logger.warning("bus %s: opening failed (%s); try %d of %d", kwargs.get("channel"), err,
                           attempt + 1, OPEN_ATTEMPTS)
            time.sleep(OPEN_RETRY_S)
    return opened()


def carries_remote_frames(bus: can.BusABC) -> bool:
    """Every python-can interface carries remote frames but socketcand (its rawmode has none)."""
    return not type(bus).__module__.startswith("can.interfaces.socketcand")


def is_kernel_bus(bus: can.BusABC) -> bool:
    """A python-can bus on a kernel SocketCAN interface (can0 on the Orin, vcan0 in CI)."""
    try:
        from can.interfaces.socketcan import SocketcanBus
    except ImportError:  # pragma: no cover - python-can always ships it
        return False
    return isinstance(bus, SocketcanBus)
