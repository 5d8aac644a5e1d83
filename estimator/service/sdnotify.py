"""systemd notification protocol in a few stdlib lines; a no-op without NOTIFY_SOCKET."""

from __future__ import annotations

import os
import socket
import time

RETRY_S = 0.5                          # how long READY=1, STOPPING=1, RELOADING=1 wait for room in the queue
DROPPABLE = ("STATUS=", "WATCHDOG=")   # lines a full queue may lose

class SdNotify:
    """Sends READY=1, WATCHDOG=1, STOPPING=1, STATUS=... to systemd (datagram on NOTIFY_SOCKET)."""

    def __init__(self, address: str | None = None) -> None:
        addr = address if address is not None else os.environ.get("NOTIFY_SOCKET", "")
        self._addr = "\0" + addr[1:] if addr.startswith("@") else addr
        self._sock: socket.socket | None = None
        if self._addr:
            self._sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)

    @property
    def enabled(self) -> bool:
        """True when running under systemd with Type=notify."""
        return self._sock is not None

    def notify(self, state: str) -> None:
        """Send one state line without ever blocking the daemon for long: a receiver that does not read
        fills its queue (10 datagrams by default on Linux), and a blocking send would then stall the
        thread that sends (a stop, at worst, until SIGKILL). ``STATUS=`` and ``WATCHDOG=`` lines are
        dropped when the queue is full (the next one will do); other states are retried for up to
        :data:`RETRY_S`. Other errors are ignored (systemd may have gone away at shutdown)."""
        if self._sock is None:
            return
        data = state.encode()
        deadline = time.monotonic() + RETRY_S
        while True:
            try:
                self._sock.sendto(data, socket.MSG_DONTWAIT, self._addr)
                return
            except BlockingIOError:
                if state.startswith(DROPPABLE) or time.monotonic() > deadline:
                    return
                time.sleep(0.01)
            except OSError:
                return

    @staticmethod
    def watchdog_interval_s() -> float | None:
        """Half of WATCHDOG_USEC (the recommended ping interval), or None if no watchdog is set."""
        usec = os.environ.get("WATCHDOG_USEC")
        pid = os.environ.get("WATCHDOG_PID")
        if not usec or (pid and pid != str(os.getpid())):
            return None
        try:
            return max(int(usec) / 2e6, 0.05)
        except ValueError:
            return None
