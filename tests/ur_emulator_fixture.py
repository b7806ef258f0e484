"""Start and stop ``mocks.ur_emulator`` processes for tests, and talk to their dashboard.

The emulator must be a separate process: the ur-rtde constructors hold the GIL while they block.
Each emulator owns one loopback address (127.0.0.2, 127.0.0.3, ...) since UR ports are fixed.
"""

from __future__ import annotations

import json
import socket
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
PORTS = (29999, 30003, 30004)


@dataclass
class EmulatorProcess:
    """A running emulator: its address, process, and dashboard helpers."""

    host: str
    proc: subprocess.Popen

    def command(self, line: str, *, timeout: float = 5.0) -> str:
        """Send one dashboard line (real or ``emulator ...``) and return the reply line."""
        with socket.create_connection((self.host, 29999), timeout) as s:
            s.settimeout(timeout)
            reader = s.makefile("r", encoding="utf-8", newline="\n")
            reader.readline()  # banner
            s.sendall((line + "\n").encode())
            return reader.readline().strip()

    def state(self) -> dict:
        """The emulator's own view: process id, joints, pose, runtime state, safety bits, faults."""
        return json.loads(self.command("emulator state"))


def ports_open(host: str, *, timeout: float = 0.2) -> bool:
    """True if all three UR ports accept a connection on ``host``."""
    for port in PORTS:
        try:
            socket.create_connection((host, port), timeout).close()
        except OSError:
            return False
    return True


def wait_ports(host: str, proc: subprocess.Popen | None = None, *,
               timeout: float = 10.0) -> None:
    """Block until ``host`` serves all UR ports; fail early if ``proc`` died."""
    deadline = time.monotonic() + timeout
    while not ports_open(host):
        if proc is not None and proc.poll() is not None:
            raise RuntimeError(f"ur_emulator on {host} exited with code {proc.returncode}")
        if time.monotonic() > deadline:
            raise TimeoutError(f"ur_emulator on {host} did not open its ports in {timeout} s")
        time.sleep(0.02)


@contextmanager
def running_emulator(*args: str, first: int = 2, last: int = 60) -> Iterator[EmulatorProcess]:
    """Run ``python -m mocks.ur_emulator --host 127.0.0.N ARGS`` for the block; always reap it.

    Takes the first address from 127.0.0.``first`` on whose UR ports nothing answers and where
    our emulator (checked by its process id) got the ports, so test sessions running side by
    side never share an emulator.
    """
    for n in range(first, last + 1):
        host = f"127.0.0.{n}"
        if ports_open(host):
            continue
        proc = subprocess.Popen(
            [sys.executable, "-m", "mocks.ur_emulator", "--host", host, *args],
            cwd=REPO, stdout=subprocess.DEVNULL)
        try:
            emulator = EmulatorProcess(host, proc)
            try:
                wait_ports(host, proc)
                ours = emulator.state()["pid"] == proc.pid
            except (RuntimeError, OSError, ValueError):
                ours = False
            if not ours:  # another session took the address in the meantime
                continue
            yield emulator
            return
        finally:
            _reap(proc)
    raise RuntimeError(f"no free loopback address in 127.0.0.{first}..{last}")


def free_host(first: int = 200, last: int = 254) -> str:
    """A loopback address on which nothing serves the UR ports (connections are refused)."""
    for n in range(first, last + 1):
        if not ports_open(f"127.0.0.{n}"):
            return f"127.0.0.{n}"
    raise RuntimeError(f"no unused loopback address in 127.0.0.{first}..{last}")


def _reap(proc: subprocess.Popen) -> None:
    """Terminate, then kill if needed; the process must be gone afterwards."""
    if proc.poll() is None:
        proc.terminate()
        try:
            proc.wait(timeout=5)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait(timeout=5)
    assert proc.poll() is not None, "ur_emulator survived teardown"
