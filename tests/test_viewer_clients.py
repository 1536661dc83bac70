"""The viewer's server meets real clients that leave abruptly, and `run --view` does what its messages say.

Clients are bare sockets speaking WebSocket (and HTTP), so that they can vanish the rudest way: a TCP reset in
the middle of the scene's backlog or of a stream of frames, with no close frame. Nothing of that may reach the
user's terminal (tornado's "Uncaught exception" tracebacks, asyncio's "exception was never retrieved"). The
command line runs in a subprocess, stdin a pipe (a script) or a pseudo-terminal (a person).
"""

from __future__ import annotations

import base64
import os
import pty
import signal
import socket
import struct
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("meshcat")
pytest.importorskip("tornado")

ROOT = Path(__file__).resolve().parents[1]
CLI = [sys.executable, "-m", "multibody_sim"]


class RawClient:
    """A WebSocket client on a bare socket (RFC 6455 handshake, masked text frames), so that it can reset."""

    def __init__(self, port: int, path: str = "/ws"):
        self.sock = socket.create_connection(("127.0.0.1", port), timeout=20)
        key = base64.b64encode(os.urandom(16)).decode()
        self.sock.sendall(
            (
                f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
                f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
            ).encode()
        )
        data = b""
        while b"\r\n\r\n" not in data:
            chunk = self.sock.recv(4096)
            if not chunk:
                raise ConnectionError("the server closed the connection during the handshake")
            data += chunk
        head, self.received = data.split(b"\r\n\r\n", 1)
        assert b" 101 " in head.split(b"\r\n")[0], head

    def send_text(self, text: str) -> None:
        payload, mask = text.encode(), os.urandom(4)
        assert len(payload) < 126
        masked = bytes(b ^ mask[i % 4] for i, b in enumerate(payload))
        self.sock.sendall(bytes([0x81, 0x80 | len(payload)]) + mask + masked)

    def read(self, n: int) -> int:
        """Read until n bytes (frames included) have arrived or the server closed; returns the count."""
        got = len(self.received)
        while got < n:
            chunk = self.sock.recv(65536)
            if not chunk:
                break
            got += len(chunk)
        return got

    def reset(self) -> None:
        """Vanish: SO_LINGER 0 makes close() send a TCP reset instead of a polite shutdown."""
        self.sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
        self.sock.close()


def http_reset(port: int, path: str) -> None:
    """An HTTP client that asks for a page and resets the connection after the first bytes of the answer."""
    sock = socket.create_connection(("127.0.0.1", port), timeout=20)
    sock.sendall(f"GET {path} HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\n\r\n".encode())
    sock.recv(100)
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    sock.close()


SERVER = """
import sys
import numpy as np
import multibody_sim as ms
import multibody_sim.viz as viz
robot = ms.load_robot("ur5")
trajectory = ms.simulate(robot, robot.neutral(), np.zeros(robot.nv), duration=2.0, dt=1e-3)
viewer = viz.Viewer(robot, port=0, announce=False)
print(viewer.server.address[1], flush=True)
while True:  # stream frames as fast as the page may take them, until the test ends this process
    viewer.play(trajectory, speed=20.0, fps=200)
"""


def test_clients_that_drop_mid_stream_print_nothing():
    """Thirty WebSocket clients reset during the backlog or the stream, and HTTP clients reset mid-script: the
    server process prints nothing at all, and still serves a well-behaved client afterwards."""
    server = subprocess.Popen(
        [sys.executable, "-c", SERVER], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT
    )
    try:
        port = int(server.stdout.readline())  # type: ignore[union-attr]
        for i in range(30):
            client = RawClient(port)
            if i % 2:
                client.read(5000)  # into the stream of frames, not only the backlog
            client.reset()
            http_reset(port, "/main.min.js")
        time.sleep(1.0)  # time for the server to notice, and for asyncio to report futures never retrieved
        polite = RawClient(port)
        assert polite.read(100_000) >= 100_000  # still serving: the scene and frames arrive
        polite.reset()
        time.sleep(0.5)
    finally:
        server.send_signal(signal.SIGTERM)
        out, err = server.communicate(timeout=30)
    assert err == ""  # no traceback, no log line, nothing


def start_run(*extra: str, stdin: int | None = subprocess.DEVNULL) -> tuple[subprocess.Popen[str], int]:
    """`run pendulum --view` in a subprocess; returns it and the viewer's port, once its URL is printed."""
    argv = [*CLI, "run", "pendulum", "--duration", "0.5", "--view", "--view-port", "0", "--view-speed", "5", *extra]
    process = subprocess.Popen(argv, stdin=stdin, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=ROOT)
    line = process.stdout.readline()  # type: ignore[union-attr]
    assert line.startswith("view: http://127.0.0.1:"), line
    return process, int(line.rsplit(":", 1)[1].strip(" /\n"))


def lines_until(process: subprocess.Popen[str], start: str, timeout: float = 60.0) -> list[str]:
    """stdout lines up to (and including) the first one that starts with `start`."""
    seen: list[str] = []
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        line = process.stdout.readline()  # type: ignore[union-attr]
        if not line:
            break
        seen.append(line.rstrip("\n"))
        if line.startswith(start):
            return seen
    raise AssertionError(f"no line starting with {start!r} in {seen}")


def test_view_from_a_script_says_it_closes_and_survives_a_client_that_drops():
    process, port = start_run()
    try:
        lines_until(process, "view: open http://127.0.0.1:")  # it waits for a page before the run
        client = RawClient(port)
        client.send_text('{"type": "multibody_sim_loaded"}')  # what our page says once it drew the scene
        client.read(20_000)  # some of the streamed frames
        client.reset()  # the page is gone mid-run: the run carries on
        seen = lines_until(process, "view: played")
    finally:
        out, err = process.communicate(timeout=60)
    assert process.returncode == 0
    assert "status: completed" in seen
    assert seen[-1] == (
        "view: played; the viewer closes now, as stdin is not a terminal (run from a terminal to keep the page open "
        "until Ctrl-C)"
    )
    assert out == "" and err == ""  # nothing after it, no traceback
    with pytest.raises(OSError):  # and it did close: nothing listens on the port any more
        socket.create_connection(("127.0.0.1", port), timeout=2).close()


def test_view_at_a_terminal_keeps_serving_until_ctrl_c():
    main_end, terminal = pty.openpty()
    process, port = start_run(stdin=terminal)
    try:
        lines_until(process, "view: open http://127.0.0.1:")
        client = RawClient(port)
        client.send_text('{"type": "multibody_sim_loaded"}')
        seen = lines_until(process, "view: played")
        assert seen[-1] == (
            "view: played; the page keeps the recording (time slider under Open Controls); Ctrl-C to quit"
        )
        client.reset()
        time.sleep(1.0)
        assert process.poll() is None  # still serving, as it said
        late = RawClient(port)  # a page opened after the run gets the recording
        assert late.read(10_000) >= 10_000
        late.reset()
        process.send_signal(signal.SIGINT)
        out, err = process.communicate(timeout=30)
    finally:
        if process.poll() is None:
            process.kill()
        os.close(main_end)
        os.close(terminal)
    assert process.returncode == 0  # Ctrl-C is how one closes the viewer of a completed run
    assert out == "" and err == ""
