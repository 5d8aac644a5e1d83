"""The process harness the benches and the tests share: start the daemon, know when it is ready,
watch the bus, stop everything.

Readiness is a signal, never a sleep: the daemon is started with ``NOTIFY_SOCKET`` pointing at a
datagram socket of ours (the sd_notify protocol it speaks to systemd), so ``READY=1`` arrives when
its bus is open; :meth:`DaemonProcess.wait_ready` then also waits for the first heartbeat
(``EstimatorStatus`` with uptime 0) seen by a :class:`BusMonitor`, which proves the path daemon -> bus
-> us. Children are started with ``PR_SET_PDEATHSIG`` (Linux): if the harness process dies, so do they.
"""

from __future__ import annotations

import collections
import contextlib
import ctypes
import itertools
import os
import signal
import socket
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import replace
from pathlib import Path
from typing import Any

import can

from estimator.codec.records import Codec, EstimatorStatus, Record
from estimator.io.captures import open_writer, to_frame
from estimator.service.bus import open_bus, resolve

REPO = Path(__file__).resolve().parents[1]


def _die_with_parent() -> None:   # pragma: no cover (runs in the child between fork and exec)
    with contextlib.suppress(OSError, AttributeError):
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)   # PR_SET_PDEATHSIG


def spawn(args: list[str], log_path: Path | None = None, env: dict[str, str] | None = None,
          stdout: Any = subprocess.DEVNULL) -> subprocess.Popen:
    """A child Python process (``args`` after the interpreter) that dies with us; stderr to ``log_path``."""
    err = open(log_path, "w") if log_path is not None else subprocess.DEVNULL   # noqa: SIM115 (the child's, closed below)
    try:
        return subprocess.Popen([sys.executable, *args], cwd=REPO, stdout=stdout, stderr=err,
                                env=dict(os.environ, PYTHONUNBUFFERED="1", **(env or {})),
                                preexec_fn=_die_with_parent if sys.platform == "linux" else None, text=True)
    finally:
        if not isinstance(err, int):
            err.close()


def stop_process(proc: subprocess.Popen | None, sig: int = signal.SIGTERM, timeout: float = 10.0) -> int | None:
    """Signal ``proc`` and wait; SIGKILL if it does not exit in ``timeout`` s. Returns the exit code."""
    if proc is None:
        return None
    if proc.poll() is None:
        with contextlib.suppress(ProcessLookupError):
            proc.send_signal(sig)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    return proc.returncode


class NotifySocket:
    """A datagram socket speaking the receiving side of sd_notify; collects the states sent to it."""

    def __init__(self) -> None:
        self._dir = tempfile.TemporaryDirectory(prefix="notify-")
        self.path = str(Path(self._dir.name) / "notify.sock")
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(self.path)
        self.states: list[str] = []

    def wait_for(self, state: str, timeout: float, alive: Callable[[], bool], count: int = 1) -> bool:
        """Until the line ``state`` arrived ``count`` times (True), ``alive()`` turns False or timeout.
        A ``state`` ending in ``*`` matches lines by prefix (``STATUS=reload*``)."""
        def seen() -> int:
            if state.endswith("*"):
                return sum(line.startswith(state[:-1]) for line in self.states)
            return self.states.count(state)
        t_end = time.monotonic() + timeout
        while seen() < count:
            left = t_end - time.monotonic()
            if left <= 0 or not alive():
                return False
            self.sock.settimeout(min(left, 0.2))
            try:
                data = self.sock.recv(4096)
            except (TimeoutError, BlockingIOError):
                continue
            self.states.extend(data.decode(errors="replace").splitlines())
        return True

    def close(self) -> None:
        self.sock.close()
        self._dir.cleanup()


class BusMonitor(threading.Thread):
    """Receives everything on a bus (like candump), decodes it, optionally writes a candump log.

    ``records`` holds (monotonic arrival time, record) of the last ``keep`` decoded frames,
    ``heartbeats`` the EstimatorStatus ones; :meth:`wait_for` blocks until a predicate over them
    holds. Subclasses override :meth:`on_record` (called with ``cond`` held) to do more.
    """

    def __init__(self, bus_spec: str, codec: Codec | None = None, capture: Path | None = None,
                 keep: int = 200_000, only: tuple[int, ...] = ()) -> None:
        super().__init__(daemon=True, name="bus-monitor")
        # ``only``: receive just these identifiers, filtered where the bus can (the loopback hub filters
        # for its client): a monitor that only watches the estimator's output need not keep up with a flood
        spec = resolve(bus_spec)
        if only:
            spec = replace(spec, options={**spec.options, "can_filters": [{"can_id": i, "can_mask": 0x7FF}
                                                                          for i in only]})
        self.bus = open_bus(spec)
        self.codec = codec or Codec()
        self.writer = open_writer(capture) if capture else None   # format by suffix (.log: candump -L)
        self.records: collections.deque[tuple[float, Record]] = collections.deque(maxlen=keep)
        self.heartbeats: collections.deque[tuple[float, EstimatorStatus]] = collections.deque(maxlen=keep)
        self.cond = threading.Condition()
        self._stop_event = threading.Event()

    def run(self) -> None:
        while not self._stop_event.is_set():
            try:
                msg = self.bus.recv(0.05)
            except can.CanError:
                continue
            if msg is None:
                continue
            now = time.monotonic()
            if self.writer is not None:
                self.writer.on_message_received(msg)
            try:
                rec = self.codec.decode(to_frame(msg))
            except Exception:   # malformed frames are sent on purpose by some tests
                continue
            if rec is None:
                continue
            with self.cond:
                self.on_record(now, rec)
                self.cond.notify_all()

    def on_record(self, now: float, rec: Record) -> None:
        """Keep one decoded record that arrived at monotonic ``now`` (``cond`` is held)."""
        self.records.append((now, rec))
        if isinstance(rec, EstimatorStatus):
            self.heartbeats.append((now, rec))

    def wait_for(self, predicate: Callable[[BusMonitor], object], timeout: float,
                 alive: Callable[[], bool] = lambda: True) -> bool:
        """Until ``predicate(self)`` holds (True), ``alive()`` turns False, or ``timeout`` s pass (False)."""
        t_end = time.monotonic() + timeout
        with self.cond:
            while not predicate(self):
                left = t_end - time.monotonic()
                if left <= 0 or not alive():
                    return False
                self.cond.wait(min(left, 0.2))
        return True

    def recent(self, n: int) -> list[tuple[float, Record]]:
        """The last ``n`` (arrival time, record) pairs, oldest first."""
        with self.cond:
            return list(itertools.islice(reversed(self.records), n))[::-1]

    def of_type(self, kind: type, since: float = 0.0) -> list:
        """Decoded records of one type that arrived at or after monotonic ``since``."""
        with self.cond:
            return [r for t, r in self.records if t >= since and isinstance(r, kind)]

    def close(self) -> None:
        self._stop_event.set()
        if self.is_alive():
            self.join(timeout=2)
        if self.writer is not None:
            self.writer.stop()
        self.bus.shutdown()


class DaemonProcess:
    """``python -m estimator run`` as a child process with readiness by sd_notify and heartbeat."""

    def __init__(self, bus_spec: str, log_path: Path, state_dir: Path | None = None,
                 config: Path | None = None, extra: list[str] | None = None) -> None:
        self.bus_spec = bus_spec
        self.log_path = log_path
        self.args = ["-m", "estimator", "run", "--bus", bus_spec]
        # absolute: the daemon runs in the repository, the caller anywhere (a relative state directory
        # would be another one, shared by every run started elsewhere)
        if state_dir is not None:
            self.args += ["--state-dir", str(Path(state_dir).absolute())]
        if config is not None:
            self.args += ["--config", str(Path(config).absolute())]
        self.args += extra or []
        self.notify = NotifySocket()
        self.proc: subprocess.Popen | None = None
        self.spawned_at = 0.0

    @property
    def pid(self) -> int:
        assert self.proc is not None
        return self.proc.pid

    def alive(self) -> bool:
        return self.proc is not None and self.proc.poll() is None

    def start(self) -> DaemonProcess:
        self.spawned_at = time.monotonic()
        self.proc = spawn(self.args, self.log_path, env={"NOTIFY_SOCKET": self.notify.path})
        return self

    def wait_ready(self, monitor: BusMonitor, timeout: float = 120.0) -> None:
        """READY=1 on the notify socket, then the first heartbeat (uptime 0) on the bus after it."""
        t0 = time.monotonic()
        if not self.notify.wait_for("READY=1", timeout, self.alive):
            raise RuntimeError(f"estimator daemon not ready: {self.why()}")
        # the first heartbeat goes out just before READY=1: any with uptime 0 received since the start
        fresh = lambda m: any(hb.uptime_s == 0 and t >= self.spawned_at for t, hb in m.heartbeats)  # noqa: E731
        if not monitor.wait_for(fresh, timeout - (time.monotonic() - t0), self.alive):
            raise RuntimeError(f"estimator daemon sent READY=1 but no heartbeat: {self.why()}")

    def why(self) -> str:
        """Exit code and the last lines of the log, for error messages."""
        code = self.proc.poll() if self.proc is not None else None
        try:
            tail = " | ".join(self.log_path.read_text(errors="replace").strip().splitlines()[-3:])
        except OSError:
            tail = ""
        return f"{'exited with code ' + str(code) if code is not None else 'still running'}; log {self.log_path}: {tail}"

    def send_signal(self, sig: int) -> None:
        assert self.proc is not None
        self.proc.send_signal(sig)

    def stop(self, sig: int = signal.SIGTERM, timeout: float = 10.0) -> int | None:
        """Stop (SIGTERM by default) and collect the exit code."""
        code = stop_process(self.proc, sig, timeout)
        self.notify.close()
        return code


@contextlib.contextmanager
def watched_daemon(bus_spec: str, log_path: Path, capture: Path | None = None, only: tuple[int, ...] = (),
                   **kw: Any) -> Iterator[tuple[DaemonProcess, BusMonitor]]:
    """A bus monitor (writing ``capture`` if given; ``only`` these identifiers if given) and a started,
    ready daemon (``kw``: state_dir, config, extra); on exit the daemon is stopped and collected, then
    the monitor closed."""
    mon = BusMonitor(bus_spec, capture=capture, only=only)
    mon.start()
    try:
        d = DaemonProcess(bus_spec, log_path, **kw).start()
        try:
            d.wait_ready(mon)
            yield d, mon
        finally:
            d.stop()
    finally:
        mon.close()


def wait_until(condition: Callable[[], bool], timeout: float, interval: float = 0.02) -> bool:
    """Until ``condition()`` holds (True) or ``timeout`` s pass (False), checking every ``interval`` s.

    For conditions nothing notifies us of (a file written by another process); never a fixed wait.
    """
    t_end = time.monotonic() + timeout
    while not condition():
        if time.monotonic() > t_end:
            return False
        time.sleep(interval)
    return True


def rss_mb(pid: int) -> float:
    """Resident memory of a process in MB (NaN if it is gone)."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
    except OSError:
        pass
    return float("nan")


STOP_REQUESTED = threading.Event()   # a stop signal arrived (see :func:`check_stop`)


def check_stop() -> None:
    """Raise the stop a signal asked for, in a loop that waits for a run to end: the signal's own
    exception can land where Python ignores exceptions (an at-fork handler while a child process
    starts) and be lost. Call it only where the run is going on, never while unwinding."""
    if STOP_REQUESTED.is_set():
        raise KeyboardInterrupt("stop requested")


def install_stop_signals() -> None:
    """SIGTERM and SIGHUP unwind the main thread like Ctrl-C, so every ``finally`` stops its children."""
    def raise_interrupt(signum: int, _frame: object) -> None:
        STOP_REQUESTED.set()
        raise KeyboardInterrupt(f"signal {signum}")
    for sig in (signal.SIGTERM, signal.SIGHUP):
        signal.signal(sig, raise_interrupt)
