"""A loopback CAN hub for machines without SocketCAN: python-can-remote serving a virtual channel.

Every process connects with ``--bus remote:ws://127.0.0.1:PORT/``; the server relays all frames
(CAN FD included) between them, like a bus. Bound to 127.0.0.1 only.
"""

from __future__ import annotations

import socket
import subprocess
import time
from pathlib import Path

from estimator.errors import EstimatorError
from sim_bench.hardware.procs import spawn, stop_process


class HubError(EstimatorError):
    """The hub cannot start (port out of range or in use, server exited)."""


def free_port() -> int:
    """An unused TCP port on 127.0.0.1."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


class Hub:
    """Starts and stops the hub server process (context manager)."""

    def __init__(self, port: int | None = None, log_path: Path | None = None) -> None:
        if port is not None and not 1 <= port <= 65535:
            raise HubError(f"--port {port} must be within 1..65535")
        self.port = port or free_port()
        self.log_path = log_path
        self.proc: subprocess.Popen | None = None

    @property
    def spec(self) -> str:
        """The bus spec clients use."""
        return f"remote:ws://127.0.0.1:{self.port}/"

    def start(self, timeout: float = 15.0) -> Hub:
        """Start the server and wait until it accepts connections; HubError if it cannot."""
        try:
            with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
                s.bind(("127.0.0.1", self.port))
        except OSError as exc:
            raise HubError(f"cannot serve the hub on 127.0.0.1:{self.port}: {exc.strerror or exc}") from None
        self.proc = spawn(["-m", "can_remote", "--interface", "virtual", "--channel", f"hub{self.port}",
                           "--host", "127.0.0.1", "--port", str(self.port), "--fd"], self.log_path)
        t_end = time.monotonic() + timeout
        while time.monotonic() < t_end:
            if self.proc.poll() is not None:
                raise HubError(f"CAN hub exited with code {self.proc.returncode} (see {self.log_path})")
            try:
                with socket.create_connection(("127.0.0.1", self.port), timeout=0.2):
                    return self
            except OSError:
                time.sleep(0.05)   # polling a port that is not yet open: nothing to wait on instead
        self.stop()
        raise HubError(f"CAN hub did not listen on 127.0.0.1:{self.port} within {timeout} s")

    def stop(self) -> None:
        """Stop the server (SIGTERM, then SIGKILL after 3 s)."""
        stop_process(self.proc, timeout=3)
        self.proc = None

    def __enter__(self) -> Hub:
        return self.start()

    def __exit__(self, *exc: object) -> None:
        self.stop()
