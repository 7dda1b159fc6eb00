"""Memory of the bus server under clients that never read (issue: per-client queues kept the
allocator's memory after the clients were gone).

The server runs alone in a child process (``--serve``); this process opens, per round, 40
clients that reach rawmode and never read, then floods the channel with 400,000 frames from a
raw sender, waits until the server has dropped the silent clients, and reads the child's RSS.
Figures: RSS before the first round, after each round, growth, and the peak (VmHWM).
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

REPO = Path(__file__).resolve().parent.parent
ROUNDS = 6
SILENT_CLIENTS = 40
FLOOD_FRAMES = 400_000


def serve() -> None:
    sys.path.insert(0, str(REPO))
    from virtual_can import BusEngine, SocketcandServer

    with BusEngine() as engine, SocketcandServer(engine, port=0, max_clients=SILENT_CLIENTS + 8) as server:
        print(server.port, flush=True)
        sys.stdin.read()  # until the parent closes the pipe


def status_kb(pid: int, field: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(field + ":"):
            return int(line.split()[1])
    raise KeyError(field)


def handshake(port: int, rcvbuf: int | None = None) -> socket.socket:
    sock = socket.socket()
    if rcvbuf:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, rcvbuf)  # fills at once: the server queues
    sock.settimeout(5.0)
    sock.connect(("127.0.0.1", port))
    for line, reply in ((None, b"< hi >"), (b"< open can0 >", b"< ok >"), (b"< rawmode >", b"< ok >")):
        if line:
            sock.sendall(line)
        assert sock.recv(64).startswith(reply)
    return sock


def one_round(port: int, frames: int) -> None:
    silent = [handshake(port, rcvbuf=4096) for _ in range(SILENT_CLIENTS)]
    sender = handshake(port)
    line = b"< send 181 8 11 22 33 44 55 66 77 88 >"
    batch = line * 1000
    for _ in range(frames // 1000):
        sender.sendall(batch)
    sender.sendall(b"< echo >")  # the server has read every line once it answers
    sender.settimeout(60.0)
    seen = b""
    while b"< echo >" not in seen:
        seen = seen[-16:] + sender.recv(65536)
    for sock in [*silent, sender]:
        sock.close()
    time.sleep(1.0)  # the server notices the closed sockets


def measure(rounds: int = ROUNDS, frames: int = FLOOD_FRAMES) -> dict[str, Any]:
    child = subprocess.Popen([sys.executable, __file__, "--serve"], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                             stderr=subprocess.DEVNULL,  # its "disconnecting" warnings, 240 of them
                             text=True)
    try:
        assert child.stdout is not None
        port = int(child.stdout.readline())
        time.sleep(0.5)
        start = status_kb(child.pid, "VmRSS") / 1024
        after = []
        for _ in range(rounds):
            one_round(port, frames)
            after.append(round(status_kb(child.pid, "VmRSS") / 1024, 1))
        peak = status_kb(child.pid, "VmHWM") / 1024
    finally:
        if child.stdin is not None:
            child.stdin.close()
        child.wait(20)
    return {"server_rss_start_mb": round(start, 1), "server_rss_after_rounds_mb": after,
            "server_rss_growth_mb": round(after[-1] - start, 1), "server_rss_peak_mb": round(peak, 1),
            "server_memory_rounds": f"{rounds} x ({SILENT_CLIENTS} silent clients + {frames} frames)"}


if __name__ == "__main__":
    if sys.argv[1:] == ["--serve"]:
        serve()
    else:
        import json

        print(json.dumps(measure(), indent=2))
        os._exit(0)
